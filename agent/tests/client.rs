//! The agent's map-server client against a mock server (wiremock): retries on 5xx/429 and
//! network errors only, 422 handling, conditional GET / 304.

use echomap_agent::client::{
    ClientConfig, ClientError, Contribution, Fetched, MapClient, UploadOutcome,
};
use echomap_shared::map::TransmitterMap;
use serde_json::json;
use std::time::Duration;
use wiremock::matchers::{header, header_exists, method, path};
use wiremock::{Mock, MockServer, ResponseTemplate};

fn client(base: &str) -> MapClient {
    let mut cfg = ClientConfig::new(base);
    cfg.token = Some("agent-token-0123456789".into());
    cfg.initial_backoff = Duration::from_millis(5);
    cfg.max_backoff = Duration::from_millis(20);
    cfg.max_retries = 4;
    MapClient::new(cfg).unwrap()
}

fn map_json() -> serde_json::Value {
    json!({"format": "echomap.map.v1", "hex_size_m": 2.0, "transmitters": [{
        "id": "t1", "components": [{"weight": 1.0, "mean": [1.0, 2.0, 0.0],
        "cov": [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]]}],
        "existence": 0.9, "reliability_m": 12.0, "visibility": []}]})
}

fn contribution() -> Contribution {
    Contribution {
        contributor: Some("test".into()),
        run: Some("r1".into()),
        traveled_m: Some(10.0),
        map: serde_json::from_value::<TransmitterMap>(map_json())
            .unwrap()
            .into(),
    }
}

fn problem(status: u16, slug: &str) -> ResponseTemplate {
    ResponseTemplate::new(status).set_body_raw(
        json!({"type": format!("https://echomap.invalid/problems/{slug}"), "title": "x",
               "status": status, "detail": format!("{slug} happened")})
        .to_string(),
        "application/problem+json",
    )
}

#[tokio::test]
async fn upload_retries_5xx_and_429_with_the_same_key_then_succeeds() {
    let server = MockServer::start().await;
    Mock::given(method("POST"))
        .and(path("/v1/maps/hall/contributions"))
        .respond_with(problem(503, "unavailable"))
        .up_to_n_times(2)
        .expect(2)
        .mount(&server)
        .await;
    Mock::given(method("POST"))
        .and(path("/v1/maps/hall/contributions"))
        .respond_with(ResponseTemplate::new(429).insert_header("retry-after", "0"))
        .up_to_n_times(1)
        .expect(1)
        .mount(&server)
        .await;
    Mock::given(method("POST"))
        .and(path("/v1/maps/hall/contributions"))
        .and(header("authorization", "Bearer agent-token-0123456789"))
        .and(header_exists("idempotency-key"))
        .respond_with(
            ResponseTemplate::new(201).set_body_json(json!({"contribution": 7, "version": 3})),
        )
        .expect(1)
        .mount(&server)
        .await;
    let out = client(&server.uri())
        .upload("hall", &contribution())
        .await
        .unwrap();
    let UploadOutcome::Accepted(v) = out else {
        panic!("{out:?}")
    };
    assert_eq!(v["version"], 3);
    let keys: Vec<String> = server
        .received_requests()
        .await
        .unwrap()
        .iter()
        .map(|r| r.headers["idempotency-key"].to_str().unwrap().to_owned())
        .collect();
    assert_eq!(keys.len(), 4);
    assert!(
        keys.iter().all(|k| k == &keys[0]),
        "a retry changed the key: {keys:?}"
    );
}

#[tokio::test]
async fn a_4xx_is_never_retried() {
    for (status, slug) in [
        (422, "invalid-field"),
        (400, "bad-request"),
        (401, "unauthorized"),
        (409, "conflict"),
    ] {
        let server = MockServer::start().await;
        Mock::given(method("POST"))
            .respond_with(problem(status, slug))
            .expect(1)
            .mount(&server)
            .await;
        match client(&server.uri()).upload("hall", &contribution()).await {
            Err(ClientError::Status {
                status: s, detail, ..
            }) => {
                assert_eq!(s, status);
                assert_eq!(detail, format!("{slug} happened"));
            }
            other => panic!("{status}: {other:?}"),
        }
    }
}

#[tokio::test]
async fn an_unmatched_upload_is_reported_as_rejected() {
    let server = MockServer::start().await;
    Mock::given(method("POST"))
        .respond_with(problem(422, "unmatched"))
        .expect(1)
        .mount(&server)
        .await;
    let out = client(&server.uri())
        .upload("hall", &contribution())
        .await
        .unwrap();
    assert!(matches!(out, UploadOutcome::Rejected(p) if p["status"] == 422));
}

#[tokio::test]
async fn an_undecided_upload_is_reported_as_undecided_and_sent_again_with_a_new_key() {
    let server = MockServer::start().await;
    Mock::given(method("POST"))
        .respond_with(problem(422, "undecided"))
        .expect(2)
        .mount(&server)
        .await;
    let c = client(&server.uri());
    let first = c.upload("hall", &contribution()).await.unwrap();
    assert!(matches!(first, UploadOutcome::Undecided(p) if p["status"] == 422));
    let again = c.upload_again("hall", &contribution(), 7).await.unwrap();
    assert!(matches!(again, UploadOutcome::Undecided(_)));
    // a deliberate new attempt after a refusal carries its own Idempotency-Key (the server
    // would answer a reused key with the stored refusal)
    let keys: Vec<String> = server
        .received_requests()
        .await
        .unwrap()
        .iter()
        .map(|r| {
            r.headers
                .get("idempotency-key")
                .unwrap()
                .to_str()
                .unwrap()
                .to_owned()
        })
        .collect();
    assert_eq!(keys.len(), 2);
    assert_ne!(keys[0], keys[1]);
}

#[tokio::test]
async fn conditional_get_sends_the_version_and_handles_304() {
    let server = MockServer::start().await;
    Mock::given(method("GET"))
        .and(path("/v1/maps/hall"))
        .and(header("if-none-match", "\"3\""))
        .respond_with(ResponseTemplate::new(304).insert_header("etag", "\"3\""))
        .expect(1)
        .mount(&server)
        .await;
    let mut served = map_json();
    served["map"] = json!("hall");
    served["version"] = json!(4);
    served["contributions"] = json!(4);
    Mock::given(method("GET"))
        .and(path("/v1/maps/hall"))
        .respond_with(ResponseTemplate::new(200).set_body_json(served))
        .expect(1)
        .mount(&server)
        .await;
    let c = client(&server.uri());
    assert!(matches!(
        c.fetch("hall", Some(3)).await.unwrap(),
        Fetched::NotModified
    ));
    let Fetched::Fresh(prior) = c.fetch("hall", None).await.unwrap() else {
        panic!()
    };
    assert_eq!(
        (prior.name.as_str(), prior.version, prior.contributions),
        ("hall", 4, 4)
    );
    assert_eq!(prior.map.len(), 1);
}

#[tokio::test]
async fn an_unreachable_server_is_retried_then_reported() {
    // a port nobody listens on
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    match client(&format!("http://127.0.0.1:{port}"))
        .fetch("hall", None)
        .await
    {
        Err(ClientError::Unreachable { attempts, .. }) => assert_eq!(attempts, 5),
        other => panic!("{other:?}"),
    }
}
