//! `echomap-agent`: simulate, run Channel-SLAM, evaluate, run crowds and experiments.

mod cli;

use clap::Parser;

// The filter clones and frees small component vectors at a high rate from every rayon
// worker (copy-on-write transmitters after resampling); glibc's allocator showed as ~8 % of
// a 4000-particle profile.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    cli::run(cli::Cli::parse())
}
