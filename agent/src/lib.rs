//! echomap agent library: the scenario simulator (`sim`), plotting (`plot`) and the CLI; the
//! Channel-SLAM filter, evaluation and the server client join here as they land.

pub mod cli;
pub mod client;
pub mod eval;
pub mod evaluate;
pub mod filter;
pub mod mrclam;
pub mod output;
pub mod plot;
pub mod remote;
pub mod run;
pub mod sim;
