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
/// coloured by SNR (the simulator's counterpart of seed 002 Fig. 7).
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
