//! `Application::build` binds the listener (port 0 allowed) and opens the database;
//! `run_until` serves until a shutdown signal, lets in-flight requests finish, then closes
//! the database.

use crate::auth::TokenStore;
use crate::config::Config;
use crate::heads::ReplicaCache;
use crate::state::{AppState, SharedState};
use crate::storage::Storage;
use anyhow::Context;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;

#[derive(Debug)]
pub struct Application {
    listener: TcpListener,
    state: SharedState,
}

impl Application {
    pub async fn build(config: Config) -> anyhow::Result<Self> {
        config.validate().map_err(anyhow::Error::msg)?;
        let tokens = match &config.token_file {
            Some(path) => TokenStore::load(path)?,
            None => TokenStore::default(),
        };
        if tokens.is_empty() {
            tracing::warn!("no tokens configured: every write will be refused (401)");
        }
        let storage = Storage::open_with(
            &config.database_url,
            config.read_connections,
            Duration::from_secs(config.database_timeout_s),
        )
        .await?;
        let listener = TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        crate::metrics::handle();
        let state = Arc::new(AppState::new(storage, tokens, config));
        Ok(Application { listener, state })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.listener
            .local_addr()
            .expect("a bound listener has an address")
    }

    pub fn state(&self) -> SharedState {
        self.state.clone()
    }

    /// Serves until `shutdown` resolves, then waits for in-flight requests (at most the
    /// configured grace period) and closes the database.
    pub async fn run_until(
        self,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> anyhow::Result<()> {
        let state = self.state.clone();
        let grace = Duration::from_secs(state.config.shutdown_grace_s);
        let (signalled_tx, signalled_rx) = tokio::sync::oneshot::channel::<()>();
        let router = crate::routes::app(state.clone()).layer(
            tower_http::trace::TraceLayer::new_for_http()
                .make_span_with(
                    tower_http::trace::DefaultMakeSpan::new().level(tracing::Level::DEBUG),
                )
                .on_response(
                    tower_http::trace::DefaultOnResponse::new().level(tracing::Level::DEBUG),
                ),
        );
        let serve = axum::serve(self.listener, router).with_graceful_shutdown(async move {
            shutdown.await;
            tracing::info!("shutting down: no new connections, finishing in-flight requests");
            let _ = signalled_tx.send(());
        });
        // `--replica-cache listen` on PostgreSQL: the task that hears heads move
        let listening = match state.storage.pg_side_pool() {
            Some(pool) if state.config.replica_cache == ReplicaCache::Listen => Some(tokio::spawn(
                crate::heads::listen(pool, state.heads.clone(), Duration::from_secs(1)),
            )),
            _ => None,
        };
        let serving = tokio::spawn(async move { serve.await });
        let mut serving = serving;
        tokio::select! {
            r = &mut serving => { r.context("server task")?.context("serving")?; }
            _ = async {
                let _ = signalled_rx.await;
                tokio::time::sleep(grace).await;
            } => {
                tracing::warn!("grace period over; dropping remaining connections");
                serving.abort();
            }
        }
        if let Some(task) = listening {
            task.abort();
        }
        state.storage.close().await;
        tracing::info!("database closed");
        Ok(())
    }
}

/// A future that resolves on SIGINT or SIGTERM. The handlers are installed when this is
/// called, not when the future is first polled: the server's shutdown future first runs on
/// another task, and a SIGTERM arriving right after start-up (before that task ran) would
/// otherwise still have its default action and kill the process without closing the database.
pub fn shutdown_signal() -> impl Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let int = signal(SignalKind::interrupt());
        let term = signal(SignalKind::terminate());
        async move {
            let wait = |s: std::io::Result<tokio::signal::unix::Signal>| async move {
                match s {
                    Ok(mut s) => {
                        s.recv().await;
                    }
                    Err(_) => std::future::pending::<()>().await,
                }
            };
            tokio::select! { _ = wait(int) => {}, _ = wait(term) => {} }
        }
    }
    #[cfg(not(unix))]
    {
        async {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}
