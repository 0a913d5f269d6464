//! Server settings as a plain value: the binary fills it from flags and environment variables,
//! tests and embedders from [`Config::for_database`] and field updates.

use crate::heads::ReplicaCache;
use std::fmt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::str::FromStr;

/// How the matcher scores a hypothesis's inliers (the location term of Ulmschneider et al.
/// 2021 eq. 18).
pub use echomap_shared::matching::MatchScore;

/// How log lines are written to stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// human-readable lines
    Text,
    /// one JSON object per line (for log shippers)
    Json,
}

impl LogFormat {
    /// Every format, by its name.
    pub const ALL: [(&'static str, LogFormat); 2] =
        [("text", LogFormat::Text), ("json", LogFormat::Json)];
}

impl FromStr for LogFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        by_name(&Self::ALL, s, "log format")
    }
}

impl fmt::Display for LogFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(name_of(&Self::ALL, self))
    }
}

/// The value named `s` in a table of (name, value); the error lists the names.
pub(crate) fn by_name<T: Copy>(
    all: &[(&'static str, T)],
    s: &str,
    what: &str,
) -> Result<T, String> {
    all.iter()
        .find(|(name, _)| *name == s)
        .map(|(_, v)| *v)
        .ok_or_else(|| {
            let names: Vec<&str> = all.iter().map(|(n, _)| *n).collect();
            format!("unknown {what} {s:?} ({})", names.join(" or "))
        })
}

/// The name of `v` in a table of (name, value).
pub(crate) fn name_of<T: PartialEq>(all: &[(&'static str, T)], v: &T) -> &'static str {
    all.iter().find(|(_, x)| x == v).map_or("?", |(n, _)| *n)
}

/// The defaults of every setting (the binary's flags show them).
pub mod defaults {
    /// listen address
    pub const LISTEN: &str = "127.0.0.1:8080";
    /// database URL
    pub const DATABASE_URL: &str = "sqlite://echomap.db";
    /// largest accepted request body, bytes
    pub const BODY_LIMIT: usize = 8 * 1024 * 1024;
    /// sustained writes per second per token
    pub const RATE_LIMIT_PER_S: u32 = 20;
    /// burst of writes per token
    pub const RATE_LIMIT_BURST: u32 = 100;
    /// rejected contributions a contributor may have in any 24 hours
    pub const REJECTED_QUOTA_PER_DAY: u32 = 50;
    /// connections in the read pool
    pub const READ_CONNECTIONS: u32 = 4;
    /// weight of the visibility term in the matching score
    pub const MATCH_VISIBILITY_WEIGHT: f64 = 1.0;
    /// squared Mahalanobis distance within which an unmatched transmitter is absorbed (0: never)
    pub const MERGE_ABSORB_CHI2: f64 = 0.0;
    /// seconds to wait for a database connection
    pub const DATABASE_TIMEOUT_S: u64 = 60;
    /// seconds in-flight requests get after SIGTERM/SIGINT
    pub const SHUTDOWN_GRACE_S: u64 = 30;
}

/// `echomap-server` settings (see `echomap-server --help` for each one's meaning).
#[derive(Debug, Clone)]
pub struct Config {
    /// address to listen on; port 0 picks a free port
    pub listen: SocketAddr,
    /// a SQLite URL or file path, or a PostgreSQL URL
    pub database_url: String,
    /// token file (`<token> <contributor> <maps>` per line); without it every write is refused
    pub token_file: Option<PathBuf>,
    /// largest accepted request body, bytes (larger → 413)
    pub body_limit: usize,
    /// sustained writes per second allowed per token; above → 429
    pub rate_limit_per_s: u32,
    /// burst of writes a token may make at once
    pub rate_limit_burst: u32,
    /// rejected contributions a contributor may have in any 24 hours (then 429)
    pub rejected_quota_per_day: u32,
    /// connections in the read pool
    pub read_connections: u32,
    /// log line format
    pub log_format: LogFormat,
    /// weight of the visibility term in the matching score (0: positions alone)
    pub match_visibility_weight: f64,
    /// how matching scores a hypothesis's inliers
    pub match_score: MatchScore,
    /// squared Mahalanobis distance within which an unmatched transmitter is absorbed
    pub merge_absorb_chi2: f64,
    /// PostgreSQL: seconds to wait for a connection
    pub database_timeout_s: u64,
    /// PostgreSQL: how a replica knows its cached head is current
    pub replica_cache: ReplicaCache,
    /// seconds in-flight requests get to finish after SIGTERM/SIGINT
    pub shutdown_grace_s: u64,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: defaults::LISTEN.parse().expect("literal address"),
            database_url: defaults::DATABASE_URL.to_string(),
            token_file: None,
            body_limit: defaults::BODY_LIMIT,
            rate_limit_per_s: defaults::RATE_LIMIT_PER_S,
            rate_limit_burst: defaults::RATE_LIMIT_BURST,
            rejected_quota_per_day: defaults::REJECTED_QUOTA_PER_DAY,
            read_connections: defaults::READ_CONNECTIONS,
            log_format: LogFormat::Text,
            match_visibility_weight: defaults::MATCH_VISIBILITY_WEIGHT,
            match_score: MatchScore::Msac,
            merge_absorb_chi2: defaults::MERGE_ABSORB_CHI2,
            database_timeout_s: defaults::DATABASE_TIMEOUT_S,
            replica_cache: ReplicaCache::Check,
            shutdown_grace_s: defaults::SHUTDOWN_GRACE_S,
        }
    }
}

impl Config {
    /// Defaults for a server on `database_url` listening on a free loopback port (tests and
    /// embedding).
    pub fn for_database(database_url: impl Into<String>) -> Self {
        Config {
            database_url: database_url.into(),
            listen: "127.0.0.1:0".parse().expect("literal address"),
            ..Config::default()
        }
    }

    /// Checks what the type cannot: the matching and merging weights are finite and ≥ 0, the
    /// pools and limits are not empty.
    pub fn validate(&self) -> Result<(), String> {
        let non_negative = [
            ("match_visibility_weight", self.match_visibility_weight),
            ("merge_absorb_chi2", self.merge_absorb_chi2),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be a finite number ≥ 0, got {v}"));
            }
        }
        let positive = [
            ("read_connections", self.read_connections as u64),
            ("rate_limit_per_s", self.rate_limit_per_s as u64),
            ("rate_limit_burst", self.rate_limit_burst as u64),
            ("rejected_quota_per_day", self.rejected_quota_per_day as u64),
            ("body_limit", self.body_limit as u64),
        ];
        for (name, v) in positive {
            if v == 0 {
                return Err(format!("{name} must be at least 1"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_formats_and_replica_caches_read_and_print_by_name() {
        for (name, f) in LogFormat::ALL {
            assert_eq!(name.parse::<LogFormat>().unwrap(), f);
            assert_eq!(f.to_string(), name);
        }
        for (name, c) in ReplicaCache::ALL {
            assert_eq!(name.parse::<ReplicaCache>().unwrap(), c);
            assert_eq!(c.to_string(), name);
        }
        assert!(
            "xml"
                .parse::<LogFormat>()
                .unwrap_err()
                .contains("text or json")
        );
        assert!("poll".parse::<ReplicaCache>().is_err());
    }

    #[test]
    fn validation_refuses_negative_weights_and_empty_pools() {
        assert!(Config::default().validate().is_ok());
        let bad = |f: fn(&mut Config)| {
            let mut c = Config::default();
            f(&mut c);
            c.validate().unwrap_err()
        };
        assert!(bad(|c| c.match_visibility_weight = -1.0).contains("match_visibility_weight"));
        assert!(bad(|c| c.merge_absorb_chi2 = f64::NAN).contains("merge_absorb_chi2"));
        assert!(bad(|c| c.read_connections = 0).contains("read_connections"));
    }
}
