//! The merge worker of a map: uploads to one map queue here and are integrated in arrival
//! order. Whatever queued meanwhile forms the next batch: its uploads are matched and merged
//! one after another (each against the map the previous one produced) on the blocking pool,
//! then committed together in one transaction — one fsync per batch instead of one per
//! upload (group commit). While a batch commits, the next one is already integrated against
//! the head the commit will leave (pipelining). Different maps have different workers and
//! merge in parallel.

use crate::api::ContributionAccepted;
use crate::delta::{self, Encoding};
use crate::error::{ApiError, ApiResult, problem_body};
pub use crate::job::Job;
use crate::merge::{Outcome, correspondences, integrate, seed_of};
use crate::state::{AppState, MapRef, SharedState, render_json};
use crate::storage::{CommitError, NewVersion, PendingCommit, Respond};
use echomap_shared::geometry::Transform2;
use echomap_shared::map::TransmitterMap;
use echomap_shared::matching::MatchDecision;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::mpsc;

/// Most uploads committed in one transaction.
pub const MAX_BATCH: usize = 64;

/// Queues `job` on the worker of `row`'s map (starting it if needed).
pub fn submit(app: &SharedState, row: &MapRef, job: Job) -> Result<(), ApiError> {
    let tx = app.merge_queue(row.id, || {
        let (tx, rx) = mpsc::unbounded_channel();
        tokio::spawn(run(app.clone(), row.clone(), rx));
        tx
    });
    tx.send(job)
        .map_err(|_| ApiError::Unavailable("the merge worker of this map stopped".into()))
}

/// Most batches integrated ahead of their predecessor's commit before the worker lets a
/// rollback of the map take its turn.
const MAX_PIPELINED: usize = 8;

/// The map a batch is integrated against: the committed head, or the head the batch being
/// committed will leave.
#[derive(Clone)]
struct Base {
    version: i64,
    contributions: i64,
    map: Option<Arc<TransmitterMap>>,
}

/// A batch integrated and ready to commit.
struct Prepared {
    base: Base,
    entries: Vec<PendingCommit>,
    /// jobs in the order of `entries`
    jobs: Vec<Job>,
    /// the map after the batch, when it accepted anything
    last_map: Option<Arc<TransmitterMap>>,
    /// its stored document (the batch's last version is stored whole)
    last_doc: Option<String>,
    accepted: i64,
}

impl Prepared {
    /// The base the next batch is integrated against if this one commits.
    fn head(&self) -> Base {
        Base {
            version: self.base.version + self.accepted,
            contributions: self.base.contributions + self.accepted,
            map: self.last_map.clone().or_else(|| self.base.map.clone()),
        }
    }
}

/// The merge worker: integrates a batch, then — while that batch commits — integrates the
/// next one against the head the first will leave (pipelining: matching and merging on the
/// blocking pool overlap the SQLite commit). If a commit fails with a moved version or a
/// duplicate key, the batch integrated behind it is discarded and both are re-integrated
/// against the stored head, in their original order.
async fn run(app: SharedState, row: MapRef, mut rx: mpsc::UnboundedReceiver<Job>) {
    let mut waiting: Vec<Job> = Vec::new();
    loop {
        if waiting.is_empty() {
            match rx.recv().await {
                Some(j) => waiting.push(j),
                None => return,
            }
        }
        fill(&mut rx, &mut waiting);
        // rollbacks of this map take the same lock
        let lock = app.map_lock(row.id);
        let _merging = lock.lock().await;
        let base = match app.current(&row).await {
            Ok(c) => Base {
                version: c.version,
                contributions: c.contributions,
                map: c.map.clone(),
            },
            Err(e) => {
                fail_all(
                    std::mem::take(&mut waiting),
                    "reading the current version",
                    e,
                );
                continue;
            }
        };
        let Some(mut prepared) = prepare(&app, &row, std::mem::take(&mut waiting), base).await
        else {
            continue;
        };
        for round in 1.. {
            let head = prepared.head();
            let committing = tokio::spawn(commit(app.clone(), row.clone(), prepared));
            let following = if round < MAX_PIPELINED {
                fill(&mut rx, &mut waiting);
                if waiting.is_empty() {
                    None
                } else {
                    prepare(&app, &row, std::mem::take(&mut waiting), head).await
                }
            } else {
                None
            };
            let retry = match committing.await {
                Ok(retry) => retry,
                Err(e) => {
                    tracing::error!(map = %row.name, error = %e, "commit task failed");
                    Vec::new()
                }
            };
            match following {
                Some(next) if retry.is_empty() => prepared = next,
                following => {
                    // re-integrate against the stored head: the retried jobs first, then the
                    // ones integrated behind them, then whatever queued meanwhile
                    if !retry.is_empty() {
                        app.forget(row.id);
                    }
                    let mut again = retry;
                    if let Some(f) = following {
                        again.extend(f.jobs);
                    }
                    again.append(&mut waiting);
                    waiting = again;
                    break;
                }
            }
        }
    }
}

/// Moves queued jobs into `batch` up to `MAX_BATCH`.
fn fill(rx: &mut mpsc::UnboundedReceiver<Job>, batch: &mut Vec<Job>) {
    while batch.len() < MAX_BATCH {
        match rx.try_recv() {
            Ok(j) => batch.push(j),
            Err(_) => break,
        }
    }
}

fn reply(job: Job, r: ApiResult<(u16, Vec<u8>)>) {
    // the client may have gone away; its retry will find the stored response
    let _ = job.reply.send(r);
}

/// Answers every job with the same internal error.
fn fail_all(jobs: Vec<Job>, what: &str, cause: impl std::fmt::Display) {
    let msg = format!("{what}: {cause}");
    for j in jobs {
        reply(j, Err(ApiError::Internal(anyhow::anyhow!("{msg}"))));
    }
}

/// Matches and merges `batch` in order (each upload against the map the previous one left)
/// on the blocking pool and renders its rows. Jobs that fail here are answered at once;
/// None when nothing is left to commit.
async fn prepare(app: &AppState, row: &MapRef, batch: Vec<Job>, base: Base) -> Option<Prepared> {
    let inputs: Vec<(Arc<TransmitterMap>, u64)> = batch
        .iter()
        .map(|j| (j.user.clone(), seed_of(&j.sha256)))
        .collect();
    let (prior0, mcfg, gcfg) = (
        base.map.clone(),
        app.match_cfg.clone(),
        app.merge_cfg.clone(),
    );
    let started = Instant::now();
    let integrated = tokio::task::spawn_blocking(move || {
        let mut prior = prior0;
        let mut out = Vec::with_capacity(inputs.len());
        for (user, seed) in inputs {
            let before = prior.clone();
            if let Some(p) = prior.as_ref().filter(|p| !p.is_empty())
                && p.hex_size_m() != user.hex_size_m()
            {
                out.push((
                    Err(ApiError::Invalid {
                        field: "map.hex_size_m".into(),
                        detail: format!("must equal the map's {} m", p.hex_size_m()),
                    }),
                    before,
                ));
                continue;
            }
            let o =
                integrate(prior.as_deref(), &user, seed, &mcfg, &gcfg).map_err(ApiError::Internal);
            if let Ok(Outcome::Initialized { map } | Outcome::Merged { map, .. }) = &o {
                prior = Some(map.clone());
            }
            out.push((o, before));
        }
        out
    })
    .await;
    let integrated = match integrated {
        Ok(v) => v,
        Err(e) => {
            fail_all(batch, "merge task failed", e);
            return None;
        }
    };
    let per_job = started.elapsed().as_secs_f64() / batch.len() as f64;
    for _ in 0..batch.len() {
        metrics::histogram!("echomap_integrate_duration_seconds").record(per_job);
    }

    let mut entries = Vec::new();
    let mut jobs: Vec<Job> = Vec::new();
    let mut last_map: Option<Arc<TransmitterMap>> = None;
    let mut accepted = 0i64;
    for (job, (outcome, prior)) in batch.into_iter().zip(integrated) {
        match outcome.and_then(|o| entry(&job, o, prior.as_deref(), &row.name)) {
            Ok((e, map)) => {
                if let Some(m) = map {
                    accepted += 1;
                    last_map = Some(m);
                }
                entries.push(e);
                jobs.push(job);
            }
            Err(err) => reply(job, Err(err)),
        }
    }
    if entries.is_empty() {
        return None;
    }
    // the newest version is stored whole: it is the map's head, and it bounds every delta
    // chain by one batch; its document is also spliced into the cached GET body
    let mut last_doc = None;
    if let (Some(v), Some(map)) = (
        entries.iter_mut().rev().find_map(|e| e.version.as_mut()),
        &last_map,
    ) {
        if v.encoding == Encoding::Delta {
            match serde_json::to_string(map.as_ref()) {
                Ok(b) => {
                    v.body = b;
                    v.encoding = Encoding::Full;
                }
                Err(e) => {
                    fail_all(jobs, "serializing the merged map", e);
                    return None;
                }
            }
        }
        last_doc = Some(v.body.clone());
    }
    Some(Prepared {
        base,
        entries,
        jobs,
        last_map,
        last_doc,
        accepted,
    })
}

/// Commits a prepared batch and answers its jobs. Returns the jobs to integrate again (the
/// version moved, or one of them was committed by another replica — that one is answered
/// from the store and left out).
async fn commit(app: SharedState, row: MapRef, p: Prepared) -> Vec<Job> {
    let Prepared {
        base,
        entries,
        mut jobs,
        last_map,
        last_doc,
        accepted,
    } = p;
    let n_entries = entries.len();
    metrics::histogram!("echomap_commit_batch_size").record(n_entries as f64);
    match app
        .storage
        .commit_batch(row.id, base.version, entries)
        .await
    {
        Ok(responses) => {
            let rejected = n_entries as i64 - accepted;
            metrics::counter!("echomap_merges_total").increment(accepted as u64);
            metrics::counter!("echomap_rejections_total").increment(rejected as u64);
            if let (Some(map), Some(doc)) = (last_map, last_doc) {
                let version = base.version + accepted;
                metrics::gauge!("echomap_map_transmitters", "map" => row.name.clone())
                    .set(map.len() as f64);
                match render_json(
                    &row.name,
                    version,
                    base.contributions + accepted,
                    Some(map),
                    &doc,
                ) {
                    Ok(c) => {
                        app.install(row.id, Arc::new(c));
                    }
                    Err(_) => app.forget(row.id),
                }
                tracing::info!(map = %row.name, version, accepted, rejected, "batch committed");
            } else if rejected > 0 {
                tracing::info!(map = %row.name, rejected, "contributions rejected");
            }
            for (job, r) in jobs.into_iter().zip(responses) {
                reply(job, Ok(r));
            }
            Vec::new()
        }
        Err(CommitError::VersionMoved { expected, actual }) => {
            // another replica committed meanwhile: re-match all
            tracing::debug!(map = %row.name, expected, actual, "version moved; re-matching");
            jobs
        }
        Err(CommitError::DuplicateKey { index }) => {
            // that upload was committed by another replica: answer it from the store
            let job = jobs.remove(index);
            let stored = app
                .storage
                .stored_response(
                    row.id,
                    &job.contribution.contributor,
                    &job.contribution.idempotency_key,
                )
                .await;
            let r = match stored {
                Ok(Some(s)) if s.request_sha256 == job.sha256 => {
                    Ok((s.response_status as u16, s.response_body))
                }
                Ok(Some(_)) => Err(ApiError::IdempotencyMismatch),
                Ok(None) => Err(ApiError::Internal(anyhow::anyhow!(
                    "duplicate key without a stored response"
                ))),
                Err(e) => Err(e.into()),
            };
            reply(job, r);
            jobs
        }
        Err(e @ (CommitError::Db(_) | CommitError::NotAccepted)) => {
            fail_all(jobs, "commit failed", e);
            Vec::new()
        }
    }
}

fn accepted_body(a: ContributionAccepted) -> (u16, Vec<u8>) {
    (
        201,
        serde_json::to_vec(&a).expect("a response always serializes"),
    )
}

/// What an accepted upload reports.
struct Accepted {
    map: Arc<TransmitterMap>,
    initialized: bool,
    map_from_agent: Transform2,
    correspondences: Vec<crate::api::Correspondence>,
    inliers: usize,
    score: f64,
    merged: usize,
    added: usize,
}

/// The row, version and stored response of one integrated upload; the merged map when accepted.
fn entry(
    job: &Job,
    outcome: Outcome,
    prior: Option<&TransmitterMap>,
    map_name: &str,
) -> ApiResult<(PendingCommit, Option<Arc<TransmitterMap>>)> {
    let mut c = job.contribution.clone();
    let mapname = map_name.to_owned();
    let accepted = match outcome {
        Outcome::Initialized { map } => Accepted {
            added: map.len(),
            map,
            initialized: true,
            map_from_agent: Transform2::IDENTITY,
            correspondences: Vec::new(),
            inliers: 0,
            score: 0.0,
            merged: 0,
        },
        Outcome::Merged {
            map,
            matched,
            stats,
        } => {
            c.inliers = Some(matched.inliers as i64);
            c.score = Some(matched.score);
            Accepted {
                correspondences: correspondences(
                    &job.user,
                    prior.expect("merged into a prior"),
                    &matched,
                ),
                map,
                initialized: false,
                map_from_agent: Transform2::from_isometry(&matched.map_from_agent),
                inliers: matched.inliers,
                score: matched.score,
                merged: stats.merged,
                added: stats.added,
            }
        }
        Outcome::Rejected { reason, matched } => {
            c.accepted = false;
            c.reason = Some(reason.clone());
            c.inliers = Some(matched.inliers as i64);
            c.score = matched.score.is_finite().then_some(matched.score);
            let undecided = matched.decision == MatchDecision::Undecided;
            let respond: Respond = Box::new(move |id, _| {
                let p = if undecided {
                    ApiError::Undecided {
                        reason,
                        contribution: id,
                    }
                } else {
                    ApiError::Unmatched {
                        reason,
                        contribution: id,
                    }
                }
                .problem();
                (p.status, problem_body(&p))
            });
            return Ok((
                PendingCommit {
                    contribution: c,
                    version: None,
                    respond,
                },
                None,
            ));
        }
    };
    let a = accepted;
    c.transform =
        Some(serde_json::to_string(&a.map_from_agent).map_err(|e| ApiError::Internal(e.into()))?);
    c.merged = Some(a.merged as i64);
    c.added = Some(a.added as i64);
    // a delta against the previous version; the batch's last version is stored whole (process)
    let (body, encoding) = match prior.and_then(|p| delta::encode(p, &a.map)) {
        Some(d) => (d, Encoding::Delta),
        None => (
            serde_json::to_string(&a.map).map_err(|e| ApiError::Internal(e.into()))?,
            Encoding::Full,
        ),
    };
    let version = NewVersion {
        body,
        encoding,
        transmitters: a.map.len() as i64,
    };
    let n_tx = a.map.len();
    let map = a.map.clone();
    let respond: Respond = Box::new(move |id, version| {
        accepted_body(ContributionAccepted {
            contribution: id,
            map: mapname,
            status: "accepted".into(),
            version: version.unwrap_or(0),
            initialized: a.initialized,
            map_from_agent: a.map_from_agent,
            correspondences: a.correspondences,
            inliers: a.inliers,
            score: a.score,
            merged: a.merged,
            added: a.added,
            transmitters: n_tx,
        })
    });
    Ok((
        PendingCommit {
            contribution: c,
            version: Some(version),
            respond,
        },
        Some(map),
    ))
}
