//! An upload on its way to its map's merge worker: what the route hands over and the channel
//! the worker answers on. Apart from the worker, so that the state that queues jobs does not
//! depend on the worker that runs them.

use crate::error::ApiResult;
use crate::storage::NewContribution;
use echomap_shared::map::TransmitterMap;
use std::sync::Arc;
use tokio::sync::oneshot;

/// One validated upload waiting for its merge.
#[derive(Debug)]
pub struct Job {
    pub user: Arc<TransmitterMap>,
    /// hex SHA-256 of the request body (RANSAC seed, idempotency check)
    pub sha256: String,
    /// the row to store; outcome fields are filled in by the worker
    pub contribution: NewContribution,
    pub reply: oneshot::Sender<ApiResult<(u16, Vec<u8>)>>,
}
