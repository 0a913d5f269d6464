//! Server configuration: every setting is a flag and an environment variable (clap).

use clap::{Parser, Subcommand, ValueEnum};
use std::net::SocketAddr;
use std::path::PathBuf;

/// How log lines are written to stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// human-readable lines
    Text,
    /// one JSON object per line (for log shippers)
    Json,
}

/// How the matcher scores a hypothesis's inliers (the location term of Ulmschneider et al.
/// 2021 eq. 18).
pub use echomap_shared::matching::MatchScore;

/// What `echomap-server` does besides serving.
#[derive(Debug, Clone, PartialEq, Eq, Subcommand)]
pub enum Command {
    /// Copy every map, contribution and version of `--database-url` into the empty database
    /// TARGET (e.g. `postgres://…` when one machine is no longer enough), with their ids, in one
    /// transaction; then exit. Stop the servers writing to the source first.
    CopyTo {
        /// database URL (or SQLite path) to copy into; its schema is created if missing
        target: String,
        /// rows read from the source at a time (memory: this many uploads or versions)
        #[arg(long, default_value_t = crate::storage::COPY_PAGE, value_parser = clap::value_parser!(u32).range(1..))]
        page_rows: u32,
    },
}

/// `echomap-server` settings.
#[derive(Debug, Clone, Parser)]
#[command(
    name = "echomap-server",
    version,
    about = "echomap map server: versioned crowd-sourced prior maps over HTTP"
)]
pub struct Config {
    /// Without a command the server serves.
    #[command(subcommand)]
    pub command: Option<Command>,

    /// Address to listen on; port 0 picks a free port (the bound address is logged).
    #[arg(long, env = "ECHOMAP_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: SocketAddr,

    /// Database: a SQLite URL or plain file path (the file is created if missing), or a
    /// PostgreSQL URL `postgres://user:password@host:port/database` (the database must exist;
    /// several server replicas may share it).
    #[arg(
        long,
        env = "ECHOMAP_DATABASE_URL",
        default_value = "sqlite://echomap.db"
    )]
    pub database_url: String,

    /// Token file: one `<token> <contributor> <maps>` per line, maps `*` or `a,b,c`; `#` comments.
    /// Without it every write is refused (401).
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,

    /// Largest accepted request body, bytes (larger → 413).
    #[arg(long, env = "ECHOMAP_BODY_LIMIT", default_value_t = 8 * 1024 * 1024)]
    pub body_limit: usize,

    /// Sustained writes per second allowed per token (PUT, POST, DELETE); above → 429.
    #[arg(long, env = "ECHOMAP_RATE_LIMIT", default_value_t = 20)]
    pub rate_limit_per_s: u32,

    /// Burst of writes a token may make at once before the rate limit applies.
    #[arg(long, env = "ECHOMAP_RATE_BURST", default_value_t = 100)]
    pub rate_limit_burst: u32,

    /// Connections in the read pool. SQLite: the write path always uses one more connection.
    /// PostgreSQL: one pool of this many plus 4 for commits.
    #[arg(long, env = "ECHOMAP_READ_CONNECTIONS", default_value_t = 4)]
    pub read_connections: u32,

    /// Log format.
    #[arg(long, env = "ECHOMAP_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,

    /// Weight of the visibility term in the matching score (Ulmschneider et al. 2021 eq. 18); 0 matches by
    /// transmitter positions alone — for maps of sensors whose detections depend on the
    /// heading (cameras), not only on the place. Every replica of a database must use the
    /// same value: a rollback's replay must rebuild the same map.
    #[arg(long, env = "ECHOMAP_MATCH_VISIBILITY_WEIGHT", default_value_t = 1.0, value_parser = non_negative)]
    pub match_visibility_weight: f64,

    /// How matching scores a hypothesis's inliers: `msac` or `likelihood` (a covariance scale
    /// fitted per hypothesis). Every replica of a database must use the same value.
    #[arg(long, env = "ECHOMAP_MATCH_SCORE", default_value_t = MatchScore::Msac)]
    pub match_score: MatchScore,

    /// Merge an upload's unmatched transmitter into the nearest map transmitter whose x, y lies
    /// within this squared Mahalanobis distance (sum of both covariances; 2 degrees of freedom,
    /// e.g. 9.21 for 99 %) instead of adding it as a new one; 0 adds every unmatched
    /// transmitter (Ulmschneider et al. 2021). Every replica of a database must use the same value.
    #[arg(long, env = "ECHOMAP_MERGE_ABSORB_CHI2", default_value_t = 0.0, value_parser = non_negative)]
    pub merge_absorb_chi2: f64,

    /// PostgreSQL only: seconds to wait for a database connection, at start-up (a database
    /// that is still starting) and per request, before failing.
    #[arg(long, env = "ECHOMAP_DATABASE_TIMEOUT_S", default_value_t = 60)]
    pub database_timeout_s: u64,

    /// PostgreSQL only: how a replica knows its cached current version of a map is still
    /// current. `check`: reads the stored head on every GET (one indexed read); a version
    /// another replica committed is served at once. `listen`: trusts the cache until a
    /// notification (LISTEN/NOTIFY on one extra connection) says the head moved; no read per
    /// GET, but another replica's commit is served only after its notification has arrived
    /// (milliseconds), and while the listening connection is down every GET reads the head.
    #[arg(long, env = "ECHOMAP_REPLICA_CACHE", value_enum, default_value_t = crate::heads::ReplicaCache::Check)]
    pub replica_cache: crate::heads::ReplicaCache,

    /// Seconds in-flight requests get to finish after SIGTERM/SIGINT.
    #[arg(long, env = "ECHOMAP_SHUTDOWN_GRACE_S", default_value_t = 30)]
    pub shutdown_grace_s: u64,
}

/// Clap value parser: a finite number ≥ 0 (also used by the agent's flags).
pub fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("{s:?} is not a non-negative number")),
    }
}

impl Config {
    /// Defaults for a server on `database_url` (tests and embedding).
    pub fn for_database(database_url: impl Into<String>) -> Self {
        let mut cfg = Config::parse_from(["echomap-server"]);
        cfg.database_url = database_url.into();
        cfg.listen = "127.0.0.1:0".parse().expect("literal address");
        cfg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_match_visibility_weight_is_a_non_negative_number() {
        let parse = |v: &str| {
            let flag = format!("--match-visibility-weight={v}");
            Config::try_parse_from(["echomap-server", flag.as_str()])
                .map(|c| c.match_visibility_weight)
        };
        assert_eq!(Config::for_database("x.db").match_visibility_weight, 1.0);
        assert_eq!(Config::for_database("x.db").match_score, MatchScore::Msac);
        let score = Config::try_parse_from(["echomap-server", "--match-score", "likelihood"]);
        assert_eq!(score.unwrap().match_score, MatchScore::Likelihood);
        assert!(Config::try_parse_from(["echomap-server", "--match-score", "ransac"]).is_err());
        assert_eq!(Config::for_database("x.db").merge_absorb_chi2, 0.0);
        let absorb = Config::try_parse_from(["echomap-server", "--merge-absorb-chi2", "9.21"]);
        assert_eq!(absorb.unwrap().merge_absorb_chi2, 9.21);
        assert!(Config::try_parse_from(["echomap-server", "--merge-absorb-chi2", "-1"]).is_err());
        assert_eq!(parse("0").unwrap(), 0.0);
        assert_eq!(parse("2.5").unwrap(), 2.5);
        for bad in ["-1", "NaN", "inf", "heavy"] {
            let e = parse(bad).unwrap_err().to_string();
            assert!(e.contains("non-negative"), "{bad}: {e}");
        }
    }
}
