use anyhow::Result;
use clap::Parser;
use echomap_server::{Application, Config, init_tracing, shutdown_signal};
use std::io::Write;

// Request handling, JSON and merging allocate many small buffers on every worker.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[tokio::main]
async fn main() -> Result<()> {
    let config = Config::parse();
    init_tracing(config.log_format);
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
