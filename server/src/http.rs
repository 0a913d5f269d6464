//! The HTTP clients of echomap: the agent's map client, the load benchmark and the tests.

/// A `reqwest` client builder, with *ring* installed as the process's rustls crypto provider.
///
/// reqwest is built without a provider (`rustls-no-provider`): its default, aws-lc-rs, took
/// 63 s of the release build on two cores, and reqwest panics in `build` when no provider is
/// installed — so every client of echomap is built from here. Installing the provider a second
/// time, or after another one was installed, changes nothing.
pub fn client_builder() -> reqwest::ClientBuilder {
    let _ = rustls::crypto::ring::default_provider().install_default();
    reqwest::Client::builder()
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_client_for_https_builds() {
        // without a provider this panics ("No rustls crypto provider is configured")
        let client = super::client_builder().https_only(true).build();
        assert!(client.is_ok(), "{client:?}");
    }
}
