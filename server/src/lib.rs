//! echomap map server: keeps the crowd-sourced prior maps, versioned, in SQLite.
//! Agents upload their user maps; the server matches (RANSAC, Ulmschneider et al. 2021 §III) and merges
//! (Ulmschneider et al. 2021 §IV) them into a new version and serves the current map to the next agent.

pub mod api;
pub mod app;
pub mod auth;
pub mod config;
pub mod delta;
pub mod error;
pub mod heads;
pub mod http;
pub mod job;
pub mod merge;
pub mod metrics;
pub mod model;
pub mod routes;
pub mod state;
pub mod storage;
pub mod synth;
pub mod viewer;
pub mod worker;

pub use app::{Application, shutdown_signal};
pub use config::{Config, LogFormat};

/// Installs the tracing subscriber (stderr; `RUST_LOG` filters, default `info`).
pub fn init_tracing(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}
