//! `run --server URL --map NAME`: fetch the prior map before the run (conditional GET against
//! the copy cached in the output directory) and upload the user map after it.
//!
//! The fetched map is saved as `prior.json` beside the run's outputs and handed to the
//! filter (matched while running, then used for association: `filter::prior`).

use crate::client::{ClientConfig, Contribution, Fetched, MapClient, UploadOutcome, parse_prior};
use crate::run::RunOutput;
use anyhow::{Context, Result};
use echomap_shared::TransmitterMap;
use std::path::Path;

#[derive(Debug)]
pub struct Remote {
    client: MapClient,
    map: String,
    contributor: String,
    rt: tokio::runtime::Runtime,
}

/// The token of a token file: its first line that is neither empty nor a `#` comment.
pub fn read_token(path: &Path) -> Result<String> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading token file {}", path.display()))?;
    text.lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap_or(l).to_owned())
        .with_context(|| format!("no token in {}", path.display()))
}

/// A client of the server at `base` (token from `token_file`, if any) and a runtime to
/// drive it from synchronous code.
pub fn connect(
    base: &str,
    token_file: Option<&Path>,
) -> Result<(MapClient, tokio::runtime::Runtime)> {
    let mut cfg = ClientConfig::new(base);
    cfg.token = token_file.map(read_token).transpose()?;
    let client = MapClient::new(cfg)?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    Ok((client, rt))
}

/// Which server and map a run talks to.
#[derive(Debug, Clone)]
pub struct RemoteSpec {
    /// base URL of the map server
    pub server: String,
    /// map name on the server
    pub map: String,
    /// file holding the bearer token
    pub token_file: Option<std::path::PathBuf>,
    /// label of this agent sent with the upload
    pub contributor: String,
}

impl Remote {
    pub fn connect(a: &RemoteSpec) -> Result<Self> {
        let (client, rt) = connect(&a.server, a.token_file.as_deref())?;
        Ok(Remote {
            client,
            map: a.map.clone(),
            contributor: a.contributor.clone(),
            rt,
        })
    }

    /// Fetches the current prior map into `dir/prior.json` (304 keeps the cached copy).
    pub fn fetch_prior(&self, dir: &Path) -> Result<TransmitterMap> {
        std::fs::create_dir_all(dir)?;
        let cache = dir.join("prior.json");
        let cached = std::fs::read_to_string(&cache)
            .ok()
            .and_then(|b| parse_prior(&b).ok());
        let fetched = self
            .rt
            .block_on(
                self.client
                    .fetch(&self.map, cached.as_ref().map(|c| c.version)),
            )
            .with_context(|| format!("fetching map {:?}", self.map))?;
        let prior = match (fetched, cached) {
            (Fetched::Fresh(p), _) => {
                std::fs::write(&cache, &p.body)?;
                p
            }
            (Fetched::NotModified, Some(c)) => c,
            (Fetched::NotModified, None) => {
                anyhow::bail!("server answered 304 to an unconditional GET")
            }
        };
        println!(
            "prior map {:?}: version {}, {} contributions, {} transmitters → {}",
            prior.name,
            prior.version,
            prior.contributions,
            prior.map.len(),
            cache.display()
        );
        Ok(prior.map)
    }

    /// Uploads the user map; prints the server's answer and saves it as `dir/upload.json`, the
    /// request body as `dir/contribution.json` (what `echomap-agent upload` sends again).
    pub fn upload(&self, out: &RunOutput, run: &str, dir: &Path) -> Result<()> {
        let c = Contribution {
            contributor: Some(self.contributor.clone()),
            run: Some(run.to_owned()),
            traveled_m: Some(out.rows.last().map(|r| r.traveled_m).unwrap_or(0.0)),
            map: out.map.clone().into(),
        };
        std::fs::write(
            dir.join(CONTRIBUTION_FILE),
            serde_json::to_string_pretty(&c)?,
        )?;
        self.send(&c, None, dir)
    }

    /// Sends the contribution saved in `dir` (by a run with `--server`) again, after the
    /// server refused it as undecided: when the map has grown, it may now decide.
    pub fn upload_again(&self, dir: &Path) -> Result<()> {
        let path = dir.join(CONTRIBUTION_FILE);
        let c: Contribution =
            serde_json::from_str(&std::fs::read_to_string(&path).with_context(|| {
                format!("reading {} (written by run --server)", path.display())
            })?)
            .with_context(|| format!("parsing {}", path.display()))?;
        let last = std::fs::read_to_string(dir.join(UPLOAD_FILE))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok());
        let status = last.as_ref().and_then(|v| v["status"].as_str());
        if status == Some("accepted") {
            anyhow::bail!(
                "{} was already merged (see {}); it is not sent twice",
                path.display(),
                dir.join(UPLOAD_FILE).display()
            );
        }
        let refused = last
            .as_ref()
            .and_then(|v| v["response"]["contribution"].as_i64());
        self.send(&c, refused, dir)
    }

    fn send(&self, c: &Contribution, refused: Option<i64>, dir: &Path) -> Result<()> {
        let outcome = self
            .rt
            .block_on(async {
                match refused {
                    Some(id) => self.client.upload_again(&self.map, c, id).await,
                    None => self.client.upload(&self.map, c).await,
                }
            })
            .with_context(|| format!("uploading to map {:?}", self.map))?;
        let saved = match &outcome {
            UploadOutcome::Accepted(v) => {
                println!(
                    "uploaded: contribution {} → map {:?} version {} ({} merged, {} added, {} inliers)",
                    v["contribution"],
                    self.map,
                    v["version"],
                    v["merged"],
                    v["added"],
                    v["inliers"]
                );
                serde_json::json!({"status": "accepted", "response": v})
            }
            UploadOutcome::Rejected(p) => {
                println!(
                    "upload rejected (map unchanged): {}",
                    p["detail"].as_str().unwrap_or("?")
                );
                serde_json::json!({"status": "rejected", "response": p})
            }
            UploadOutcome::Undecided(p) => {
                println!(
                    "upload undecided (map unchanged): {}\nthe map is kept in {}; send it again later with: echomap-agent upload {} --server URL --map {}",
                    p["detail"].as_str().unwrap_or("?"),
                    dir.join(CONTRIBUTION_FILE).display(),
                    dir.display(),
                    self.map
                );
                serde_json::json!({"status": "undecided", "response": p})
            }
        };
        std::fs::write(dir.join(UPLOAD_FILE), serde_json::to_string_pretty(&saved)?)?;
        Ok(())
    }
}

/// The request body of a run's upload, kept in its output directory.
pub const CONTRIBUTION_FILE: &str = "contribution.json";
/// The server's answer to a run's last upload.
pub const UPLOAD_FILE: &str = "upload.json";
