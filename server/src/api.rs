//! Request and response bodies of API v1: the wire contract lives in `echomap_shared::api`,
//! which clients share.

pub use echomap_shared::api::*;
