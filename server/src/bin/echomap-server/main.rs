use anyhow::Result;
mod cli;

use clap::Parser;
use cli::{Cli, Command};
use echomap_server::storage::{Storage, redact, sqlite_file};
use echomap_server::{Application, Config, init_tracing, shutdown_signal};
use std::io::Write;

// Request handling, JSON and merging allocate many small buffers on every worker.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[tokio::main]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let config = cli.config();
    init_tracing(config.log_format);
    if let Some(Command::CopyTo { target, page_rows }) = &cli.command {
        return copy_to(&config, target, *page_rows).await;
    }
    let app = Application::build(config).await?;
    // handlers first: a SIGTERM sent as soon as the address line appears must be graceful
    let shutdown = shutdown_signal();
    let addr = app.local_addr();
    tracing::info!(%addr, "echomap-server listening");
    // one machine-readable line on stdout, for scripts and tests that start on port 0
    println!("echomap-server listening on http://{addr}");
    std::io::stdout().flush()?;
    app.run_until(shutdown).await
}

/// `echomap-server --database-url SOURCE copy-to TARGET`.
async fn copy_to(config: &Config, target: &str, page_rows: u32) -> Result<()> {
    let source_url = &config.database_url;
    // opening a SQLite database creates a missing file: refuse a source that is not there
    if let Some(path) = sqlite_file(source_url) {
        anyhow::ensure!(
            path.is_file(),
            "the source database {} does not exist",
            path.display()
        );
    }
    let timeout = std::time::Duration::from_secs(config.database_timeout_s);
    let source = Storage::open_with(source_url, 1, timeout).await?;
    let into = Storage::open_with(target, 1, timeout).await?;
    let copied = source.copy_into(&into, page_rows).await?;
    into.close().await;
    source.close().await;
    println!(
        "copied {} maps, {} contributions and {} versions from {} to {}",
        copied.maps,
        copied.contributions,
        copied.versions,
        redact(source_url),
        redact(target)
    );
    Ok(())
}
