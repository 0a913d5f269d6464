//! The agent's own map-server client against the OpenAPI document the server serves: every
//! request body the client sends and every response body it receives validates (JSON Schema
//! 2020-12) against the schema the document declares for that operation and status, so the
//! client and the document cannot drift apart. Real server on loopback, real HTTP.

use echomap_agent::client::{ClientConfig, Contribution, Fetched, MapClient, UploadOutcome};
use echomap_agent::local_server::LocalServer;
use echomap_shared::TransmitterMap;
use serde_json::{Value, json};

/// The schema the document declares for `method path` — the request body (`status` None) or
/// the response with `status` — checked against `value`.
fn conforms(doc: &Value, method: &str, path: &str, status: Option<&str>, value: &Value) {
    let op = &doc["paths"][path][method];
    let content = match status {
        None => &op["requestBody"]["content"],
        Some(s) => &op["responses"][s]["content"],
    };
    let schema = content
        .as_object()
        .and_then(|c| c.values().next())
        .map(|m| m["schema"].clone())
        .unwrap_or_else(|| panic!("{method} {path} {status:?}: no schema in the document"));
    let root = json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "allOf": [schema],
        "components": doc["components"],
    });
    let validator = jsonschema::validator_for(&root)
        .unwrap_or_else(|e| panic!("{method} {path}: the declared schema does not compile: {e}"));
    let errors: Vec<String> = validator
        .iter_errors(value)
        .map(|e| format!("{} at {}", e, e.instance_path()))
        .collect();
    assert!(
        errors.is_empty(),
        "{method} {path} {status:?}: the body does not conform to the document: {errors:?}"
    );
}

fn user_map(world: &[[f64; 3]], seed: u64) -> TransmitterMap {
    serde_json::from_value(echomap_server::synth::user_map(world, seed, 0.9, 0.1, 2)).unwrap()
}

fn contribution(map: &TransmitterMap, run: &str) -> Contribution {
    Contribution {
        contributor: Some("contract-test".into()),
        run: Some(run.into()),
        traveled_m: Some(120.0),
        map: map.clone().into(),
    }
}

#[test]
fn the_agents_client_and_the_openapi_document_agree() {
    let server = LocalServer::start().unwrap();
    let token = echomap_agent::remote::read_token(&server.token_file).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let doc: Value = echomap_agent::client::http_client_builder()
            .build()
            .unwrap()
            .get(format!("{}/openapi.json", server.url))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let mut cfg = ClientConfig::new(server.url.clone());
        cfg.token = Some(token);
        let client = MapClient::new(cfg).unwrap();
        client.create_map("hall").await.unwrap();
        let world = echomap_server::synth::world(3, 25);
        let contributions = "/v1/maps/{map}/contributions";
        let mut versions = Vec::new();
        for (k, seed) in [11u64, 12].into_iter().enumerate() {
            let c = contribution(&user_map(&world, seed), &format!("walk-{k}"));
            conforms(
                &doc,
                "post",
                contributions,
                None,
                &serde_json::to_value(&c).unwrap(),
            );
            match client.upload("hall", &c).await.unwrap() {
                UploadOutcome::Accepted(v) => {
                    conforms(&doc, "post", contributions, Some("201"), &v);
                    versions.push(v["version"].as_i64().unwrap());
                }
                other => panic!("upload {k} refused: {other:?}"),
            }
        }
        assert_eq!(versions, [1, 2]);
        let Fetched::Fresh(head) = client.fetch("hall", None).await.unwrap() else {
            panic!("an unconditional GET answered 304");
        };
        let body: Value = serde_json::from_str(&head.body).unwrap();
        conforms(&doc, "get", "/v1/maps/{map}", Some("200"), &body);
        assert!(matches!(
            client.fetch("hall", Some(head.version)).await.unwrap(),
            Fetched::NotModified
        ));
        let v1 = client.fetch_version("hall", 1).await.unwrap();
        let body: Value = serde_json::from_str(&v1.body).unwrap();
        conforms(
            &doc,
            "get",
            "/v1/maps/{map}/versions/{n}",
            Some("200"),
            &body,
        );
        // a partial user map matched remotely
        let partial = user_map(&world, 13);
        conforms(
            &doc,
            "post",
            "/v1/maps/{map}/match",
            None,
            &json!({ "map": &partial }),
        );
        let answer = client.match_map("hall", &partial).await.unwrap();
        conforms(&doc, "post", "/v1/maps/{map}/match", Some("200"), &answer);
        assert_eq!(answer["accepted"], true, "{answer}");
        // a map of elsewhere: refused, with a problem document as declared
        let elsewhere = user_map(&echomap_server::synth::world(99, 25), 99);
        match client
            .upload("hall", &contribution(&elsewhere, "elsewhere"))
            .await
            .unwrap()
        {
            UploadOutcome::Rejected(p) | UploadOutcome::Undecided(p) => {
                conforms(&doc, "post", contributions, Some("422"), &p)
            }
            UploadOutcome::Accepted(v) => panic!("a map of elsewhere merged: {v}"),
        }
    });
    server.stop().unwrap();
}
