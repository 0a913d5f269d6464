//! `echomap-server`: the crowd-sourced map server. Until the server issue lands it only
//! reports its version.

use clap::Parser;

#[derive(Debug, Parser)]
#[command(
    name = "echomap-server",
    version,
    about = "echomap map server (HTTP API not implemented yet)"
)]
struct Cli {}

fn main() {
    let _ = Cli::parse();
    println!(
        "echomap-server {} — the HTTP API is not implemented yet",
        env!("CARGO_PKG_VERSION")
    );
}
