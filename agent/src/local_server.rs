//! A map server on loopback for `experiment` and `demo`: the real `echomap-server`
//! application (axum + SQLite file) on its own tokio runtime thread, with a fresh database
//! and a token file in a temporary directory. Agents talk to it over HTTP like to any server.

use anyhow::{Context, Result};
use std::path::PathBuf;

#[derive(Debug)]
pub struct LocalServer {
    pub url: String,
    pub token_file: PathBuf,
    pub database: PathBuf,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<()>>>,
    _dir: tempfile::TempDir,
}

impl LocalServer {
    /// Starts a server on 127.0.0.1 (free port) with a new SQLite file.
    pub fn start() -> Result<Self> {
        Self::start_with(|_| {})
    }

    /// The same, with `adjust` applied to the server's settings last.
    pub fn start_with(adjust: impl FnOnce(&mut echomap_server::config::Config)) -> Result<Self> {
        let dir = tempfile::Builder::new()
            .prefix("echomap-server-")
            .tempdir()
            .context("creating a temporary directory for the server")?;
        let token_file = dir.path().join("tokens.txt");
        // A token unique to this process and directory; it never leaves the machine.
        let token = format!(
            "local-{}-{}",
            std::process::id(),
            dir.path()
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("x")
                .replace(|c: char| !c.is_ascii_alphanumeric(), "")
        );
        std::fs::write(&token_file, format!("{token} experiment *\n"))?;
        let database = dir.path().join("echomap.db");
        let mut cfg = echomap_server::config::Config::for_database(database.display().to_string());
        cfg.token_file = Some(token_file.clone());
        // a crowd uploads quickly in a row; the write limit guards public servers
        cfg.rate_limit_per_s = 1000;
        cfg.rate_limit_burst = 1000;
        cfg.shutdown_grace_s = 5;
        adjust(&mut cfg);
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("echomap-server".into())
            .spawn(move || -> Result<()> {
                let rt = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()?;
                rt.block_on(async move {
                    let app = match echomap_server::app::Application::build(cfg).await {
                        Ok(a) => a,
                        Err(e) => {
                            let _ = addr_tx.send(Err(e.to_string()));
                            return Ok(());
                        }
                    };
                    let _ = addr_tx.send(Ok(app.local_addr()));
                    app.run_until(async move {
                        let _ = stop_rx.await;
                    })
                    .await
                })
            })?;
        let addr = addr_rx
            .recv()
            .context("the server thread ended before binding")?
            .map_err(|e| anyhow::anyhow!("starting the map server: {e}"))?;
        Ok(LocalServer {
            url: format!("http://{addr}"),
            token_file,
            database,
            shutdown: Some(stop_tx),
            thread: Some(thread),
            _dir: dir,
        })
    }

    /// Stops accepting, finishes in-flight requests, closes the database.
    pub fn stop(mut self) -> Result<()> {
        self.halt()
    }

    fn halt(&mut self) -> Result<()> {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            t.join()
                .map_err(|_| anyhow::anyhow!("the server thread panicked"))??;
        }
        Ok(())
    }
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        let _ = self.halt();
    }
}
