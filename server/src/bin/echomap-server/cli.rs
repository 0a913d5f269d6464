//! The command line of `echomap-server`: every setting is a flag and an environment variable.

use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{Parser, Subcommand};
use echomap_server::config::{Config, LogFormat, MatchScore, defaults};
use echomap_server::heads::ReplicaCache;
use std::net::SocketAddr;
use std::path::PathBuf;

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
        #[arg(long, default_value_t = echomap_server::storage::COPY_PAGE, value_parser = clap::value_parser!(u32).range(1..))]
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
pub struct Cli {
    /// Without a command the server serves.
    #[command(subcommand)]
    pub command: Option<Command>,

    /// Address to listen on; port 0 picks a free port (the bound address is logged).
    #[arg(long, env = "ECHOMAP_LISTEN", default_value = defaults::LISTEN)]
    pub listen: SocketAddr,

    /// Database: a SQLite URL or plain file path (the file is created if missing), or a
    /// PostgreSQL URL `postgres://user:password@host:port/database` (the database must exist;
    /// several server replicas may share it).
    #[arg(long, env = "ECHOMAP_DATABASE_URL", default_value = defaults::DATABASE_URL)]
    pub database_url: String,

    /// Token file: one `<token> <contributor> <maps>` per line, maps `*` or `a,b,c`; `#` comments.
    /// Without it every write is refused (401).
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,

    /// Largest accepted request body, bytes (larger → 413).
    #[arg(long, env = "ECHOMAP_BODY_LIMIT", default_value_t = defaults::BODY_LIMIT, value_parser = clap::value_parser!(usize))]
    pub body_limit: usize,

    /// Sustained writes per second allowed per token (PUT, POST, DELETE); above → 429.
    #[arg(long, env = "ECHOMAP_RATE_LIMIT", default_value_t = defaults::RATE_LIMIT_PER_S, value_parser = clap::value_parser!(u32).range(1..))]
    pub rate_limit_per_s: u32,

    /// Burst of writes a token may make at once before the rate limit applies.
    #[arg(long, env = "ECHOMAP_RATE_BURST", default_value_t = defaults::RATE_LIMIT_BURST, value_parser = clap::value_parser!(u32).range(1..))]
    pub rate_limit_burst: u32,

    /// Rejected contributions (uploads that match no map) a contributor may have in any 24
    /// hours, over all maps and replicas; above → 429 until the oldest ages out. Keeps one
    /// misbehaving contributor from filling the contribution table.
    #[arg(long, env = "ECHOMAP_REJECTED_QUOTA", default_value_t = defaults::REJECTED_QUOTA_PER_DAY, value_parser = clap::value_parser!(u32).range(1..))]
    pub rejected_quota_per_day: u32,

    /// Connections in the read pool. SQLite: the write path always uses one more connection.
    /// PostgreSQL: one pool of this many plus 4 for commits.
    #[arg(long, env = "ECHOMAP_READ_CONNECTIONS", default_value_t = defaults::READ_CONNECTIONS, value_parser = clap::value_parser!(u32).range(1..))]
    pub read_connections: u32,

    /// Log format.
    #[arg(long, env = "ECHOMAP_LOG_FORMAT", default_value = "text",
          value_parser = PossibleValuesParser::new(LogFormat::ALL.map(|(n, _)| n))
              .map(|s| s.parse::<LogFormat>().expect("a listed value")))]
    pub log_format: LogFormat,

    /// Weight of the visibility term in the matching score (Ulmschneider et al. 2021 eq. 18); 0 matches by
    /// transmitter positions alone — for maps of sensors whose detections depend on the
    /// heading (cameras), not only on the place. Every replica of a database must use the
    /// same value: a rollback's replay must rebuild the same map.
    #[arg(long, env = "ECHOMAP_MATCH_VISIBILITY_WEIGHT", default_value_t = defaults::MATCH_VISIBILITY_WEIGHT, value_parser = non_negative)]
    pub match_visibility_weight: f64,

    /// How matching scores a hypothesis's inliers: `msac` or `likelihood` (a covariance scale
    /// fitted per hypothesis). Every replica of a database must use the same value.
    #[arg(long, env = "ECHOMAP_MATCH_SCORE", default_value_t = MatchScore::Msac)]
    pub match_score: MatchScore,

    /// Merge an upload's unmatched transmitter into the nearest map transmitter whose x, y lies
    /// within this squared Mahalanobis distance (sum of both covariances; 2 degrees of freedom,
    /// e.g. 9.21 for 99 %) instead of adding it as a new one; 0 adds every unmatched
    /// transmitter (Ulmschneider et al. 2021). Every replica of a database must use the same value.
    #[arg(long, env = "ECHOMAP_MERGE_ABSORB_CHI2", default_value_t = defaults::MERGE_ABSORB_CHI2, value_parser = non_negative)]
    pub merge_absorb_chi2: f64,

    /// PostgreSQL only: seconds to wait for a database connection, at start-up (a database
    /// that is still starting) and per request, before failing.
    #[arg(long, env = "ECHOMAP_DATABASE_TIMEOUT_S", default_value_t = defaults::DATABASE_TIMEOUT_S)]
    pub database_timeout_s: u64,

    /// PostgreSQL only: how a replica knows its cached current version of a map is still
    /// current. `check`: reads the stored head on every GET (one indexed read); a version
    /// another replica committed is served at once. `listen`: trusts the cache until a
    /// notification (LISTEN/NOTIFY on one extra connection) says the head moved; no read per
    /// GET, but another replica's commit is served only after its notification has arrived
    /// (milliseconds), and while the listening connection is down every GET reads the head.
    #[arg(long, env = "ECHOMAP_REPLICA_CACHE", default_value = "check",
          value_parser = PossibleValuesParser::new(ReplicaCache::ALL.map(|(n, _)| n))
              .map(|s| s.parse::<ReplicaCache>().expect("a listed value")))]
    pub replica_cache: ReplicaCache,

    /// Seconds in-flight requests get to finish after SIGTERM/SIGINT.
    #[arg(long, env = "ECHOMAP_SHUTDOWN_GRACE_S", default_value_t = defaults::SHUTDOWN_GRACE_S)]
    pub shutdown_grace_s: u64,
}

impl Cli {
    /// The server settings these flags give.
    pub fn config(&self) -> Config {
        Config {
            listen: self.listen,
            database_url: self.database_url.clone(),
            token_file: self.token_file.clone(),
            body_limit: self.body_limit,
            rate_limit_per_s: self.rate_limit_per_s,
            rate_limit_burst: self.rate_limit_burst,
            rejected_quota_per_day: self.rejected_quota_per_day,
            read_connections: self.read_connections,
            log_format: self.log_format,
            match_visibility_weight: self.match_visibility_weight,
            match_score: self.match_score,
            merge_absorb_chi2: self.merge_absorb_chi2,
            database_timeout_s: self.database_timeout_s,
            replica_cache: self.replica_cache,
            shutdown_grace_s: self.shutdown_grace_s,
        }
    }
}

/// Clap value parser: a finite number ≥ 0.
fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("{s:?} is not a non-negative number")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flags_default_to_the_library_defaults() {
        let cli = Cli::parse_from(["echomap-server"]);
        let (a, b) = (cli.config(), Config::default());
        assert_eq!(format!("{a:?}"), format!("{b:?}"));
    }

    #[test]
    fn the_match_visibility_weight_is_a_non_negative_number() {
        let parse = |v: &str| {
            let flag = format!("--match-visibility-weight={v}");
            Cli::try_parse_from(["echomap-server", flag.as_str()])
                .map(|c| c.match_visibility_weight)
        };
        let score = Cli::try_parse_from(["echomap-server", "--match-score", "likelihood"]);
        assert_eq!(score.unwrap().match_score, MatchScore::Likelihood);
        assert!(Cli::try_parse_from(["echomap-server", "--match-score", "ransac"]).is_err());
        let absorb = Cli::try_parse_from(["echomap-server", "--merge-absorb-chi2", "9.21"]);
        assert_eq!(absorb.unwrap().merge_absorb_chi2, 9.21);
        assert!(Cli::try_parse_from(["echomap-server", "--merge-absorb-chi2", "-1"]).is_err());
        assert_eq!(parse("0").unwrap(), 0.0);
        assert_eq!(parse("2.5").unwrap(), 2.5);
        for bad in ["-1", "NaN", "inf", "heavy"] {
            let e = parse(bad).unwrap_err().to_string();
            assert!(e.contains("non-negative"), "{bad}: {e}");
        }
        let json = Cli::try_parse_from(["echomap-server", "--log-format", "json"]).unwrap();
        assert_eq!(json.log_format, LogFormat::Json);
        assert!(Cli::try_parse_from(["echomap-server", "--log-format", "xml"]).is_err());
        let listen = Cli::try_parse_from(["echomap-server", "--replica-cache", "listen"]).unwrap();
        assert_eq!(listen.replica_cache, ReplicaCache::Listen);
        assert!(Cli::try_parse_from(["echomap-server", "--read-connections", "0"]).is_err());
    }
}
