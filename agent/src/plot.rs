//! Plots (PNG via the bitmap backend, SVG via the SVG backend) with an embedded font, so
//! nothing depends on fonts installed on the machine.

use crate::sim::Scenario;
use crate::sim::simulate::visible_virtual_transmitters;
use anyhow::{Result, anyhow, bail};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::{ColorMap, ViridisRGB};
use std::path::Path;
use std::sync::Once;

static FONT: Once = Once::new();

/// Registers the embedded DejaVu Sans as "sans-serif" (once per process).
pub fn ensure_font() {
    FONT.call_once(|| {
        // The embedded font is a valid TrueType file; failure would be a packaging bug.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Runs `draw` on a PNG or SVG drawing area chosen by the file extension.
pub fn with_backend(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    draw_svg: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<()> {
    ensure_font();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "png" => {
            let root = BitMapBackend::new(path, size).into_drawing_area();
            draw(&root)?;
            root.present()
                .map_err(|e| anyhow!("writing {}: {e}", path.display()))
        }
        "svg" => {
            let root = SVGBackend::new(path, size).into_drawing_area();
            draw_svg(&root)?;
            root.present()
                .map_err(|e| anyhow!("writing {}: {e}", path.display()))
        }
        _ => bail!("plot file must end in .png or .svg: {}", path.display()),
    }
}

const TRACK_COLORS: [RGBColor; 6] = [
    BLUE,
    RGBColor(0, 150, 0),
    RGBColor(230, 120, 0),
    CYAN,
    RGBColor(120, 60, 0),
    RGBColor(90, 90, 90),
];

/// Draws walls, scatterers, the transmitter, the chosen tracks (all if empty) and the
/// virtual transmitters detectable along `vtx_track`.
pub fn draw_scenario(
    scenario: &Scenario,
    tracks: &[String],
    vtx_track: &str,
    out: &Path,
) -> Result<()> {
    let chosen: Vec<_> = if tracks.is_empty() {
        scenario.tracks.iter().collect()
    } else {
        tracks
            .iter()
            .map(|n| scenario.track(n))
            .collect::<Result<_, _>>()?
    };
    let vtx = match scenario.track(vtx_track) {
        Ok(t) => visible_virtual_transmitters(scenario, t, 0.5),
        Err(_) => Vec::new(),
    };
    let mut xs = vec![scenario.transmitter.position[0]];
    let mut ys = vec![scenario.transmitter.position[1]];
    for w in &scenario.walls {
        xs.extend([w.from[0], w.to[0]]);
        ys.extend([w.from[1], w.to[1]]);
    }
    for v in &vtx {
        xs.push(v.0.x);
        ys.push(v.0.y);
    }
    for t in &chosen {
        for p in &t.waypoints {
            xs.push(p[0]);
            ys.push(p[1]);
        }
    }
    let (x0, x1) = (
        xs.iter().cloned().fold(f64::INFINITY, f64::min),
        xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    );
    let (y0, y1) = (
        ys.iter().cloned().fold(f64::INFINITY, f64::min),
        ys.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    );
    let pad = 0.05 * (x1 - x0).max(y1 - y0);
    let (x0, x1, y0, y1) = (x0 - pad, x1 + pad, y0 - pad, y1 + pad);
    // equal aspect: 1000 px wide, height by the data's ratio (bounded)
    let w_px = 1000u32;
    let h_px =
        ((f64::from(w_px) - 80.0) * (y1 - y0) / (x1 - x0) + 110.0).clamp(300.0, 1600.0) as u32;
    let title = format!(
        "scenario {} — {} virtual transmitters along {}",
        scenario.name,
        vtx.len(),
        vtx_track
    );

    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let mut chart = ChartBuilder::on(root)
                .caption(&title, ("sans-serif", 22))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(45)
                .build_cartesian_2d(x0..x1, y0..y1)
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .configure_mesh()
                .x_desc("x (m)")
                .y_desc("y (m)")
                .light_line_style(WHITE.mix(0.0))
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            for w in &scenario.walls {
                chart
                    .draw_series(LineSeries::new(
                        vec![(w.from[0], w.from[1]), (w.to[0], w.to[1])],
                        BLACK.stroke_width(3),
                    ))
                    .map_err(|e| anyhow!("{e}"))?;
            }
            for (i, t) in chosen.iter().enumerate() {
                let traj = crate::sim::trajectory::Trajectory::new(&t.waypoints, t.turn_radius_m);
                let n = (traj.length_m() / 0.25).ceil() as usize;
                let pts: Vec<(f64, f64)> = (0..=n)
                    .map(|k| {
                        let (p, _) = traj.pose_at(k as f64 * 0.25);
                        (p.x, p.y)
                    })
                    .collect();
                let color = TRACK_COLORS[i % TRACK_COLORS.len()];
                let s = chart
                    .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
                    .map_err(|e| anyhow!("{e}"))?;
                if chosen.len() <= 6 {
                    s.label(t.name.clone()).legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                    });
                }
                chart
                    .draw_series(std::iter::once(Circle::new(pts[0], 5, color.filled())))
                    .map_err(|e| anyhow!("{e}"))?;
            }
            chart
                .draw_series(
                    scenario
                        .scatterers
                        .iter()
                        .map(|s| Circle::new((s.position[0], s.position[1]), 4, BLACK.filled())),
                )
                .map_err(|e| anyhow!("{e}"))?
                .label("scatterer")
                .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK.filled()));
            chart
                .draw_series(vtx.iter().filter(|v| v.2 != "physical").map(|v| {
                    let c = if v.2 == "reflection" {
                        MAGENTA
                    } else {
                        RGBColor(128, 0, 200)
                    };
                    TriangleMarker::new((v.0.x, v.0.y), 6, c.filled())
                }))
                .map_err(|e| anyhow!("{e}"))?
                .label("virtual Tx (reflection / scattering)")
                .legend(|(x, y)| TriangleMarker::new((x + 10, y), 6, MAGENTA.filled()));
            chart
                .draw_series(std::iter::once(TriangleMarker::new(
                    (
                        scenario.transmitter.position[0],
                        scenario.transmitter.position[1],
                    ),
                    9,
                    RED.filled(),
                )))
                .map_err(|e| anyhow!("{e}"))?
                .label("Tx")
                .legend(|(x, y)| TriangleMarker::new((x + 10, y), 7, RED.filled()));
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            Ok(())
        }};
    }
    with_backend(out, (w_px, h_px), |root| body!(root), |root| body!(root))
}

/// Propagation distance of every reported component versus the user's travelled distance,
/// coloured by SNR (the simulator's counterpart of Gentner et al. 2016 Fig. 7).
pub fn draw_components(
    log: &echomap_shared::log::MeasurementLog,
    truth: &echomap_shared::log::GroundTruth,
    title: &str,
    out: &Path,
) -> Result<()> {
    let mut travelled = Vec::with_capacity(truth.poses.len());
    let mut acc = 0.0;
    for (i, p) in truth.poses.iter().enumerate() {
        if i > 0 {
            let q = &truth.poses[i - 1];
            acc += (p.x - q.x).hypot(p.y - q.y);
        }
        travelled.push(acc);
    }
    let pts: Vec<(f64, f64, f64)> = log
        .snapshots
        .iter()
        .zip(&travelled)
        .flat_map(|(s, &t)| s.components.iter().map(move |c| (t, c.d, c.snr_db)))
        .collect();
    let d_max = pts.iter().map(|p| p.1).fold(1.0, f64::max) * 1.05;
    let s_min = pts.iter().map(|p| p.2).fold(f64::INFINITY, f64::min);
    let s_max = pts.iter().map(|p| p.2).fold(f64::NEG_INFINITY, f64::max);
    let x_max = acc.max(1.0);
    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let mut chart = ChartBuilder::on(root)
                .caption(title, ("sans-serif", 22))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..x_max, 0.0..d_max)
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .configure_mesh()
                .x_desc("user travelled distance (m)")
                .y_desc("propagation distance d (m)")
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            let span = (s_max - s_min).max(1e-9);
            chart
                .draw_series(pts.iter().map(|&(x, d, snr)| {
                    let f = (snr - s_min) / span;
                    Circle::new((x, d), 1, ViridisRGB.get_color(f).filled())
                }))
                .map_err(|e| anyhow!("{e}"))?;
            Ok(())
        }};
    }
    with_backend(out, (1000, 600), |root| body!(root), |root| body!(root))
}

/// Estimated track and map (transmitter means with 2σ ellipses) over the true track and
/// true virtual transmitters (local frame).
pub fn draw_track_and_map(
    rows: &[crate::eval::TrackRow],
    map: &echomap_shared::TransmitterMap,
    truth: Option<&echomap_shared::log::GroundTruth>,
    out: &Path,
) -> Result<()> {
    let est: Vec<(f64, f64)> = rows.iter().map(|r| (r.x, r.y)).collect();
    let tru: Vec<(f64, f64)> = rows
        .iter()
        .filter_map(|r| r.truth.map(|t| (t.true_x, t.true_y)))
        .collect();
    let txs: Vec<(f64, f64, [f64; 3])> = map
        .transmitters()
        .iter()
        .filter(|t| t.existence >= 0.5)
        .map(|t| {
            let (m, p) = t.moments();
            (m.x, m.y, [p[(0, 0)], p[(0, 1)], p[(1, 1)]])
        })
        .filter(|t| t.2[0] + t.2[2] < 25.0)
        .collect();
    let true_tx: Vec<(f64, f64)> = truth
        .map(|t| {
            t.transmitters
                .iter()
                .map(|v| (v.state[0], v.state[1]))
                .collect()
        })
        .unwrap_or_default();
    let all: Vec<(f64, f64)> = est
        .iter()
        .chain(&tru)
        .chain(true_tx.iter())
        .copied()
        .chain(txs.iter().map(|t| (t.0, t.1)))
        .collect();
    let (x0, x1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.0), a.1.max(p.0))
    });
    let (y0, y1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.1), a.1.max(p.1))
    });
    let pad = 0.05 * (x1 - x0).max(y1 - y0).max(1.0);
    let (x0, x1, y0, y1) = (x0 - pad, x1 + pad, y0 - pad, y1 + pad);
    let w_px = 1000u32;
    let h_px =
        ((f64::from(w_px) - 80.0) * (y1 - y0) / (x1 - x0) + 110.0).clamp(300.0, 1600.0) as u32;
    let ellipse = |x: f64, y: f64, c: [f64; 3]| -> Vec<(f64, f64)> {
        // 2σ ellipse of the 2×2 covariance [[a, b], [b, d]]
        let m = nalgebra::Matrix2::new(c[0], c[1], c[1], c[2]);
        let l = m
            .cholesky()
            .map(|ch| ch.l())
            .unwrap_or_else(nalgebra::Matrix2::zeros);
        (0..=36)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 36.0;
                let v = l * nalgebra::Vector2::new(a.cos(), a.sin()) * 2.0;
                (x + v.x, y + v.y)
            })
            .collect()
    };
    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let mut chart = ChartBuilder::on(root)
                .caption("estimated track and map (local frame)", ("sans-serif", 22))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(45)
                .build_cartesian_2d(x0..x1, y0..y1)
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .configure_mesh()
                .x_desc("x (m)")
                .y_desc("y (m)")
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            if !tru.is_empty() {
                chart
                    .draw_series(LineSeries::new(tru.clone(), BLACK.stroke_width(2)))
                    .map_err(|e| anyhow!("{e}"))?
                    .label("true track")
                    .legend(|(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(2))
                    });
                chart
                    .draw_series(
                        true_tx
                            .iter()
                            .map(|p| Cross::new(*p, 5, RED.stroke_width(2))),
                    )
                    .map_err(|e| anyhow!("{e}"))?
                    .label("true virtual Tx")
                    .legend(|(x, y)| Cross::new((x + 10, y), 5, RED.stroke_width(2)));
            }
            chart
                .draw_series(LineSeries::new(est.clone(), BLUE.stroke_width(2)))
                .map_err(|e| anyhow!("{e}"))?
                .label("estimate")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
            for t in &txs {
                chart
                    .draw_series(LineSeries::new(
                        ellipse(t.0, t.1, t.2),
                        MAGENTA.stroke_width(1),
                    ))
                    .map_err(|e| anyhow!("{e}"))?;
            }
            chart
                .draw_series(
                    txs.iter()
                        .map(|t| TriangleMarker::new((t.0, t.1), 5, MAGENTA.filled())),
                )
                .map_err(|e| anyhow!("{e}"))?
                .label("estimated Tx (2σ)")
                .legend(|(x, y)| TriangleMarker::new((x + 10, y), 5, MAGENTA.filled()));
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            Ok(())
        }};
    }
    with_backend(out, (w_px, h_px), |root| body!(root), |root| body!(root))
}

/// MAE and RMSE against travelled distance for one run.
pub fn draw_error(rows: &[crate::eval::TrackRow], out: &Path) -> Result<()> {
    let curves = vec![
        (
            "MAE (eq. 27)".to_string(),
            BLUE,
            rows.iter()
                .filter_map(|r| r.truth.map(|t| (r.traveled_m, t.mae_m)))
                .collect(),
        ),
        (
            "RMSE".to_string(),
            RED,
            rows.iter()
                .filter_map(|r| r.truth.map(|t| (r.traveled_m, t.rmse_m)))
                .collect(),
        ),
    ];
    draw_curves(
        "position error vs travelled distance",
        "error (m)",
        &curves,
        out,
    )
}

/// Draws `curves` on `chart` with a legend at `pos` (font size `font`): thin lines for labels
/// naming a percentile, thick ones otherwise.
macro_rules! labelled_curves {
    ($chart:expr, $curves:expr, $pos:expr, $font:expr) => {{
        for (label, color, pts) in $curves {
            let color = *color;
            let thin = label.contains("95") || label.contains(" 5th") || label.contains("p5");
            let style = color.stroke_width(if thin { 1 } else { 2 });
            $chart
                .draw_series(LineSeries::new(
                    pts.iter().copied().filter(|p| p.1.is_finite()),
                    style,
                ))
                .map_err(|e| anyhow!("{e}"))?
                .label(label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
        }
        $chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", $font))
            .position($pos)
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
    }};
}

/// A labelled curve: (label, colour, points).
pub type Curve = (String, RGBColor, Vec<(f64, f64)>);

/// A line chart of several labelled curves over travelled distance.
pub fn draw_curves(title: &str, y_desc: &str, curves: &[Curve], out: &Path) -> Result<()> {
    draw_xy(title, "travelled distance (m)", y_desc, curves, out)
}

/// A line chart of several labelled curves, x from 0.
pub fn draw_xy(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    curves: &[Curve],
    out: &Path,
) -> Result<()> {
    let x_max = curves
        .iter()
        .flat_map(|c| c.2.iter().map(|p| p.0))
        .fold(1.0, f64::max);
    let y_max = curves
        .iter()
        .flat_map(|c| c.2.iter().map(|p| p.1))
        .filter(|v| v.is_finite())
        .fold(0.1, f64::max)
        * 1.05;
    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let mut chart = ChartBuilder::on(root)
                .caption(title, ("sans-serif", 22))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..x_max, 0.0..y_max)
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .configure_mesh()
                .x_desc(x_desc)
                .y_desc(y_desc)
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            labelled_curves!(chart, curves, SeriesLabelPosition::UpperLeft, 14);
            Ok(())
        }};
    }
    with_backend(out, (1000, 600), |root| body!(root), |root| body!(root))
}

/// Several line charts of labelled curves over travelled distance, in a grid of `cols`
/// columns, one panel per (title, curves), all on the same y range; thin curves for labels
/// naming a percentile, as in [`draw_curves`].
pub fn draw_panels(
    title: &str,
    y_desc: &str,
    panels: &[(String, Vec<Curve>)],
    cols: usize,
    out: &Path,
) -> Result<()> {
    anyhow::ensure!(!panels.is_empty() && cols >= 1, "nothing to draw");
    let all = || panels.iter().flat_map(|p| p.1.iter());
    let y_max = all()
        .flat_map(|c| c.2.iter().map(|p| p.1))
        .filter(|v| v.is_finite())
        .fold(0.1, f64::max)
        * 1.05;
    let rows = panels.len().div_ceil(cols);
    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let root = root
                .titled(title, ("sans-serif", 22))
                .map_err(|e| anyhow!("{e}"))?;
            for (area, (name, curves)) in root.split_evenly((rows, cols)).iter().zip(panels) {
                let x_max = curves
                    .iter()
                    .flat_map(|c| c.2.iter().map(|p| p.0))
                    .fold(1.0, f64::max);
                let mut chart = ChartBuilder::on(area)
                    .caption(name, ("sans-serif", 16))
                    .margin(8)
                    .x_label_area_size(30)
                    .y_label_area_size(40)
                    .build_cartesian_2d(0.0..x_max, 0.0..y_max)
                    .map_err(|e| anyhow!("{e}"))?;
                chart
                    .configure_mesh()
                    .x_desc("travelled distance (m)")
                    .y_desc(y_desc)
                    .draw()
                    .map_err(|e| anyhow!("{e}"))?;
                labelled_curves!(chart, curves, SeriesLabelPosition::UpperRight, 12);
            }
            Ok(())
        }};
    }
    let size = (500 * cols as u32, 40 + 320 * rows as u32);
    with_backend(out, size, |root| body!(root), |root| body!(root))
}

/// The channel waterfall of a sampled CIR: power per delay sample (summed over the elements,
/// in dB over the noise) against time, with the detections of `log` on top, coloured by track
/// (PNG only: one cell per snapshot and sample).
pub fn draw_waterfall(
    cir: &crate::radio::cir::Cir,
    noise_variance: f64,
    log: &echomap_shared::log::MeasurementLog,
    out: &Path,
) -> Result<()> {
    let meta = &cir.meta;
    let (n, m) = (meta.samples, meta.elements_m.len());
    let mps = meta.metres_per_sample();
    let times: Vec<f64> = meta.snapshots.iter().map(|s| s.t).collect();
    let (t0, t1) = match (times.first(), times.last()) {
        (Some(a), Some(b)) => (*a, b.max(a + 1e-3)),
        _ => bail!("the CIR has no snapshot"),
    };
    let dt = if times.len() > 1 {
        (t1 - t0) / (times.len() - 1) as f64
    } else {
        1.0
    };
    let d0 = meta.delay_origin_m;
    let d1 = d0 + n as f64 * mps;
    let scale = 1.0 / (m as f64 * noise_variance.max(f64::MIN_POSITIVE));
    let cells: Vec<(f64, f64, f64)> = times
        .iter()
        .enumerate()
        .flat_map(|(k, &t)| {
            let y = cir.snapshot(k);
            (0..n).map(move |i| {
                let p: f64 = (0..m).map(|e| f64::from(y[e * n + i].norm_sqr())).sum();
                (t, d0 + i as f64 * mps, 10.0 * (p * scale).max(1e-3).log10())
            })
        })
        .collect();
    let top = cells.iter().map(|c| c.2).fold(0.0, f64::max).max(1.0);
    let dots: Vec<(f64, f64, u64)> = log
        .snapshots
        .iter()
        .flat_map(|s| s.components.iter().map(move |c| (s.t, c.d, c.track)))
        .collect();
    ensure_font();
    if !out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        bail!("the waterfall is a PNG: {}", out.display());
    }
    let root = BitMapBackend::new(out, (1200, 700)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "channel waterfall: power over noise (dB), tracked paths on top",
            ("sans-serif", 22),
        )
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(55)
        .build_cartesian_2d(t0..t1 + dt, d0..d1)
        .map_err(|e| anyhow!("{e}"))?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("time (s)")
        .y_desc("propagation distance (m)")
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    chart
        .draw_series(cells.iter().map(|&(t, d, db)| {
            let c = ViridisRGB.get_color((db / top).clamp(0.0, 1.0));
            Rectangle::new([(t, d), (t + dt, d + mps)], c.filled())
        }))
        .map_err(|e| anyhow!("{e}"))?;
    chart
        .draw_series(dots.iter().map(|&(t, d, track)| {
            let c = TRACK_COLORS[(track % TRACK_COLORS.len() as u64) as usize];
            Circle::new((t + 0.5 * dt, d), 1, c.mix(0.9).filled())
        }))
        .map_err(|e| anyhow!("{e}"))?;
    root.present()
        .map_err(|e| anyhow!("writing {}: {e}", out.display()))
}

/// The filter's error over dead reckoning's per log: one dot per run (seed), a bar at the
/// mean of each log's runs, and dashed lines at the ratios 1 (no better than the odometry)
/// and ½. `rows` are `(log name, ratio per run)`.
pub fn draw_ratios(title: &str, rows: &[(String, Vec<f64>)], out: &Path) -> Result<()> {
    anyhow::ensure!(!rows.is_empty(), "nothing to draw");
    let n = rows.len();
    let y_max = rows
        .iter()
        .flat_map(|r| r.1.iter().copied())
        .filter(|v| v.is_finite())
        .fold(1.2, f64::max)
        * 1.4; // room above the highest run for the legend
    let names: Vec<String> = rows.iter().map(|r| r.0.clone()).collect();
    macro_rules! body {
        ($root:expr) => {{
            let root = $root;
            root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
            let mut chart = ChartBuilder::on(root)
                .caption(title, ("sans-serif", 22))
                .margin(10)
                .x_label_area_size(60)
                .y_label_area_size(55)
                .build_cartesian_2d(-0.5..(n as f64 - 0.5), 0.0..y_max)
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .configure_mesh()
                .disable_x_mesh()
                .x_labels(n)
                .x_label_formatter(&|x| {
                    let k = x.round();
                    if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < names.len() {
                        names[k as usize].clone()
                    } else {
                        String::new()
                    }
                })
                .y_desc("mean error / dead reckoning's")
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            for (level, label) in [(1.0, "1: no better than the odometry"), (0.5, "½")] {
                chart
                    .draw_series(DashedLineSeries::new(
                        [(-0.5, level), (n as f64 - 0.5, level)],
                        6,
                        4,
                        RGBColor(120, 120, 120).stroke_width(1),
                    ))
                    .map_err(|e| anyhow!("{e}"))?
                    .label(label)
                    .legend(|(x, y)| {
                        PathElement::new([(x, y), (x + 20, y)], RGBColor(120, 120, 120))
                    });
            }
            let dots = rows.iter().enumerate().flat_map(|(i, r)| {
                let k = r.1.len().max(1) as f64;
                r.1.iter().enumerate().map(move |(j, v)| {
                    // runs spread a little sideways so that equal values stay visible
                    let dx = if k > 1.0 {
                        0.3 * (j as f64 / (k - 1.0) - 0.5)
                    } else {
                        0.0
                    };
                    Circle::new((i as f64 + dx, *v), 4, BLUE.filled())
                })
            });
            chart
                .draw_series(dots)
                .map_err(|e| anyhow!("{e}"))?
                .label("one run (seed)")
                .legend(|(x, y)| Circle::new((x + 10, y), 4, BLUE.filled()));
            let means = rows.iter().enumerate().filter_map(|(i, r)| {
                let v: Vec<f64> = r.1.iter().copied().filter(|v| v.is_finite()).collect();
                (!v.is_empty()).then(|| {
                    let m = v.iter().sum::<f64>() / v.len() as f64;
                    PathElement::new(
                        [(i as f64 - 0.3, m), (i as f64 + 0.3, m)],
                        RED.stroke_width(3),
                    )
                })
            });
            chart
                .draw_series(means)
                .map_err(|e| anyhow!("{e}"))?
                .label("mean of the runs")
                .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RED.stroke_width(3)));
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 14))
                .draw()
                .map_err(|e| anyhow!("{e}"))?;
            Ok(())
        }};
    }
    with_backend(
        out,
        ((160 + 110 * n as u32).max(900), 560),
        |root| body!(root),
        |root| body!(root),
    )
}
