//! echomap agent library: the scenario simulator (`sim`), the Channel-SLAM filter
//! (`filter`), evaluation (`eval`, `evaluate`), the map-server client (`client`, `remote`),
//! crowds of agent processes (`crowd`), the cooperative experiment (`experiment`), the demo,
//! plotting, and the run configuration (`config`). The command line lives in the binary.

pub mod client;
pub mod coincidence;
pub mod config;
pub mod crowd;
#[cfg(feature = "lab")]
pub mod demo;
pub mod eval;
pub mod evaluate;
#[cfg(feature = "lab")]
pub mod experiment;
pub mod files;
pub mod filter;
#[cfg(feature = "lab")]
pub mod local_server;
pub mod mrclam;
pub mod output;
pub mod plot;
pub mod radio;
pub mod remote;
pub mod run;
pub mod sim;
