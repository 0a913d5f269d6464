//! Integration tests of the map server: the real server on 127.0.0.1:0 with a temporary SQLite
//! file, driven over HTTP with reqwest (and a few handler tests through `oneshot`).

mod common;

use common::*;
use serde_json::{Value, json};

#[tokio::test]
async fn first_contribution_initializes_and_later_ones_match_and_merge() {
    let s = TestServer::start().await;
    let c = client();
    create_map(&c, &s, "hall").await;
    let truth = world(1, 25);
    let a = contribution(user_map(&truth, 100, 0.9, 0.1), "a");
    let r = post_contribution(&c, &s, "hall", ALICE, "k-a", &a).await;
    assert_eq!(r.status(), 201);
    let ra: Value = r.json().await.unwrap();
    assert_eq!(ra["version"], 1);
    assert_eq!(ra["initialized"], true);

    let b = contribution(user_map(&truth, 200, 0.9, 0.1), "b");
    let r = post_contribution(&c, &s, "hall", BOB, "k-b", &b).await;
    assert_eq!(r.status(), 201);
    let rb: Value = r.json().await.unwrap();
    assert_eq!(rb["version"], 2);
    assert_eq!(rb["initialized"], false);
    let corr = rb["correspondences"].as_array().unwrap();
    assert!(corr.len() >= 15, "{} correspondences", corr.len());
    // the matcher must pair the two views of the same world transmitter
    for p in corr {
        let wa = p["agent"].as_str().unwrap().split('-').nth(1).unwrap();
        let wm = p["map"].as_str().unwrap().split('-').nth(1).unwrap();
        assert_eq!(wa, wm, "{p}");
    }
    assert_eq!(rb["merged"].as_u64().unwrap() as usize, corr.len());

    let cur: Value = c
        .get(s.url("/v1/maps/hall"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(cur["version"], 2);
    assert_eq!(cur["contributions"], 2);
    assert_eq!(cur["format"], "echomap.map.v1");
    assert_eq!(
        cur["transmitters"].as_array().unwrap().len(),
        rb["transmitters"].as_u64().unwrap() as usize
    );
    s.stop().await;
}

fn is_problem(r: &reqwest::Response) -> bool {
    r.headers()
        .get("content-type")
        .is_some_and(|v| v.to_str().unwrap() == "application/problem+json")
}

/// A map with three accepted contributions of world 1.
async fn seeded_map(c: &reqwest::Client, s: &TestServer, name: &str) -> Vec<Value> {
    create_map(c, s, name).await;
    let truth = world(1, 25);
    let mut bodies = Vec::new();
    for (k, seed) in [11u64, 12, 13].into_iter().enumerate() {
        let b = contribution(user_map(&truth, seed, 0.85, 0.1), &format!("run-{k}"));
        let r = post_contribution(c, s, name, ALICE, &format!("{name}-{k}"), &b).await;
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
        bodies.push(b);
    }
    bodies
}

#[tokio::test]
async fn idempotent_retry_returns_the_stored_response_byte_for_byte() {
    let s = TestServer::start().await;
    let c = client();
    seeded_map(&c, &s, "hall").await;
    let body = contribution(user_map(&world(1, 25), 77, 0.9, 0.1), "retry");
    let first = post_contribution(&c, &s, "hall", BOB, "retry-1", &body).await;
    assert_eq!(first.status(), 201);
    let first_bytes = first.bytes().await.unwrap();
    let before = dump(&s.db).await;
    for _ in 0..3 {
        let again = post_contribution(&c, &s, "hall", BOB, "retry-1", &body).await;
        assert_eq!(again.status(), 201);
        assert_eq!(again.headers()["idempotent-replayed"], "true");
        assert_eq!(again.bytes().await.unwrap(), first_bytes);
    }
    assert_eq!(dump(&s.db).await, before, "a retry must not merge twice");
    // the same key with another body
    let other = contribution(user_map(&world(1, 25), 78, 0.9, 0.1), "retry");
    let r = post_contribution(&c, &s, "hall", BOB, "retry-1", &other).await;
    assert_eq!(r.status(), 422);
    assert!(is_problem(&r));
    // the same key from another contributor is another request
    let r = post_contribution(&c, &s, "hall", ALICE, "retry-1", &other).await;
    assert_eq!(r.status(), 201);
    s.stop().await;
}

#[tokio::test]
async fn a_retry_while_the_first_is_running_gets_409() {
    let s = TestServer::start().await;
    let c = client();
    seeded_map(&c, &s, "hall").await;
    let map_id: i64 = 1;
    let body = contribution(user_map(&world(1, 25), 90, 0.9, 0.1), "slow");
    // hold the map's merge lock: whichever request registers the key first waits on it
    let lock = s.state.map_lock(map_id);
    let guard = lock.lock().await;
    let (c1, c2) = (c.clone(), c.clone());
    let (b1, b2) = (body.clone(), body.clone());
    let url = s.url("/v1/maps/hall/contributions");
    let send = |c: reqwest::Client, b: Value, url: String| async move {
        c.post(url)
            .bearer_auth(BOB)
            .header("Idempotency-Key", "same")
            .json(&b)
            .send()
            .await
            .unwrap()
    };
    let t1 = tokio::spawn(send(c1, b1, url.clone()));
    let t2 = tokio::spawn(send(c2, b2, url));
    // exactly one finishes while the lock is held, with 409
    let (first, other) = loop {
        if t1.is_finished() {
            break (t1.await.unwrap(), t2);
        }
        if t2.is_finished() {
            break (t2.await.unwrap(), t1);
        }
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    };
    assert_eq!(first.status(), 409);
    assert!(is_problem(&first));
    drop(guard);
    // the other one completes, and a later retry gets its stored response
    let other = other.await.unwrap();
    assert_eq!(other.status(), 201);
    let other_bytes = other.bytes().await.unwrap();
    let again = post_contribution(&c, &s, "hall", BOB, "same", &body).await;
    assert_eq!(again.status(), 201);
    assert_eq!(again.bytes().await.unwrap(), other_bytes);
    let page: Value = c
        .get(s.url("/v1/maps/hall/contributions"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let from_bob = page["contributions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|x| x["contributor"] == "bob")
        .count();
    assert_eq!(from_bob, 1);
    s.stop().await;
}

struct Case {
    name: &'static str,
    method: reqwest::Method,
    path: String,
    token: Option<&'static str>,
    key: Option<String>,
    content_type: Option<&'static str>,
    body: Vec<u8>,
    status: u16,
    field: Option<&'static str>,
}

fn case(name: &'static str, status: u16, body: Vec<u8>) -> Case {
    Case {
        name,
        method: reqwest::Method::POST,
        path: "/v1/maps/hall/contributions".into(),
        token: Some(ALICE),
        key: Some(format!("hostile-{}", name.replace(' ', "-"))),
        content_type: Some("application/json"),
        body,
        status,
        field: None,
    }
}

fn with_map(f: impl FnOnce(&mut Value)) -> Vec<u8> {
    let mut b = contribution(user_map(&world(1, 25), 500, 0.9, 0.1), "hostile");
    f(&mut b);
    serde_json::to_vec(&b).unwrap()
}

#[tokio::test]
async fn hostile_input_gets_its_status_and_changes_nothing() {
    let s = TestServer::start_with(|cfg| cfg.body_limit = 64 * 1024 * 1024).await;
    let c = client();
    seeded_map(&c, &s, "hall").await;
    create_map(&c, &s, "other").await;
    let good = with_map(|_| {});
    // a stored contribution whose key will be reused with another body
    let r = c
        .post(s.url("/v1/maps/hall/contributions"))
        .bearer_auth(ALICE)
        .header("Idempotency-Key", "reused")
        .header("content-type", "application/json")
        .body(good.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let huge = {
        let one = r#"{"id":"t","components":[],"existence":1,"reliability_m":0}"#;
        let mut s =
            String::from(r#"{"map":{"format":"echomap.map.v1","hex_size_m":2.0,"transmitters":["#);
        for i in 0..1_000_000 {
            if i > 0 {
                s.push(',');
            }
            s.push_str(one);
        }
        s.push_str("]}}");
        s.into_bytes()
    };

    let mut cases = vec![
        case("truncated json", 400, br#"{"map": {"format": "#.to_vec()),
        case("not json", 400, b"hello".to_vec()),
        case("empty body", 400, Vec::new()),
        case(
            "NaN literal",
            400,
            String::from_utf8(good.clone())
                .unwrap()
                .replacen("0.95", "NaN", 1)
                .into_bytes(),
        ),
        case(
            "Infinity literal",
            400,
            String::from_utf8(good.clone())
                .unwrap()
                .replacen("0.95", "Infinity", 1)
                .into_bytes(),
        ),
        case(
            "1e400",
            400,
            String::from_utf8(good.clone())
                .unwrap()
                .replacen("0.95", "1e400", 1)
                .into_bytes(),
        ),
        Case {
            field: Some("map.format"),
            ..case(
                "wrong format tag",
                422,
                with_map(|b| b["map"]["format"] = json!("echomap.map.v0")),
            )
        },
        Case {
            field: Some("map.transmitters[0].components[0].cov"),
            ..case(
                "negative variance",
                422,
                with_map(|b| {
                    b["map"]["transmitters"][0]["components"][0]["cov"][0][0] = json!(-1.0)
                }),
            )
        },
        Case {
            field: Some("map.transmitters[0].components[0].cov"),
            ..case(
                "asymmetric covariance",
                422,
                with_map(|b| {
                    b["map"]["transmitters"][0]["components"][0]["cov"][0][1] = json!(0.01)
                }),
            )
        },
        Case {
            field: Some("map.transmitters[0].components[0].cov"),
            ..case(
                "indefinite covariance",
                422,
                with_map(|b| {
                    b["map"]["transmitters"][0]["components"][0]["cov"] =
                        json!([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
                }),
            )
        },
        Case {
            field: Some("map.transmitters[0].components"),
            ..case(
                "weights not summing to 1",
                422,
                with_map(|b| b["map"]["transmitters"][0]["components"][0]["weight"] = json!(0.5)),
            )
        },
        Case {
            field: Some("map.transmitters[0].components[0].weight"),
            ..case(
                "negative weight",
                422,
                with_map(|b| b["map"]["transmitters"][0]["components"][0]["weight"] = json!(-1.0)),
            )
        },
        Case {
            field: Some("map.transmitters[0].existence"),
            ..case(
                "existence above 1",
                422,
                with_map(|b| b["map"]["transmitters"][0]["existence"] = json!(1.5)),
            )
        },
        Case {
            field: Some("map.hex_size_m"),
            ..case(
                "zero hex size",
                422,
                with_map(|b| b["map"]["hex_size_m"] = json!(0.0)),
            )
        },
        Case {
            field: Some("map.transmitters[1].id"),
            ..case(
                "duplicate ids",
                422,
                with_map(|b| {
                    b["map"]["transmitters"][1]["id"] = b["map"]["transmitters"][0]["id"].clone()
                }),
            )
        },
        Case {
            field: Some("map.transmitters[0].components[0].mean[0]"),
            ..case(
                "string NaN",
                422,
                with_map(|b| {
                    b["map"]["transmitters"][0]["components"][0]["mean"][0] = json!("NaN")
                }),
            )
        },
        Case {
            field: Some("traveled_m"),
            ..case(
                "negative distance",
                422,
                with_map(|b| b["traveled_m"] = json!(-3.0)),
            )
        },
        Case {
            field: Some("map.transmitters"),
            ..case(
                "no transmitters",
                422,
                with_map(|b| b["map"]["transmitters"] = json!([])),
            )
        },
        Case {
            field: Some("surprise"),
            ..case("unknown field", 422, with_map(|b| b["surprise"] = json!(1)))
        },
        Case {
            field: Some("map"),
            ..case("missing map", 422, br#"{"run": "x"}"#.to_vec())
        },
        Case {
            field: Some("map.transmitters"),
            ..case("10^6 transmitters", 422, huge)
        },
        case("unknown map", 404, good.clone()).with_path("/v1/maps/nowhere/contributions"),
        case("path traversal name", 400, good.clone())
            .with_path("/v1/maps/..%2F..%2Fetc%2Fpasswd/contributions"),
        case("SQL in name", 400, good.clone())
            .with_path("/v1/maps/x'%3B%20DROP%20TABLE%20maps%3B--/contributions"),
        case("65-character name", 400, good.clone())
            .with_path(&format!("/v1/maps/{}/contributions", "a".repeat(65))),
        Case {
            token: None,
            ..case("missing token", 401, good.clone())
        },
        Case {
            token: Some("not-a-valid-token-at-all"),
            ..case("invalid token", 401, good.clone())
        },
        Case {
            token: Some(CAROL),
            ..case("token for another map", 403, good.clone())
        },
        Case {
            key: None,
            ..case("missing Idempotency-Key", 400, good.clone())
        },
        Case {
            key: Some("x".repeat(300)),
            ..case("overlong Idempotency-Key", 400, good.clone())
        },
        Case {
            key: Some("reused".into()),
            ..case(
                "reused key, other body",
                422,
                with_map(|b| b["run"] = json!("changed")),
            )
        },
        Case {
            content_type: Some("text/plain"),
            ..case("wrong content type", 415, good.clone())
        },
        Case {
            method: reqwest::Method::PUT,
            path: "/v1/maps/a%2Fb".into(),
            ..case("create map named a/b", 400, Vec::new())
        },
        Case {
            method: reqwest::Method::PUT,
            token: Some(CAROL),
            path: "/v1/maps/newmap".into(),
            ..case("create map without scope", 403, Vec::new())
        },
        Case {
            method: reqwest::Method::DELETE,
            token: Some(DAVE),
            path: "/v1/maps/hall/contributions/1".into(),
            ..case("roll back another's contribution", 403, Vec::new())
        },
        Case {
            method: reqwest::Method::DELETE,
            path: "/v1/maps/hall/contributions/999".into(),
            ..case("roll back unknown contribution", 404, Vec::new())
        },
    ];
    assert!(cases.len() >= 25);
    let before = dump(&s.db).await;
    for k in cases.drain(..) {
        let mut req = c.request(k.method.clone(), s.url(&k.path)).body(k.body);
        if let Some(t) = k.token {
            req = req.bearer_auth(t);
        }
        if let Some(key) = &k.key {
            req = req.header("Idempotency-Key", key.as_str());
        }
        if let Some(ct) = k.content_type {
            req = req.header("content-type", ct);
        }
        let r = req.send().await.unwrap();
        assert_eq!(
            r.status().as_u16(),
            k.status,
            "{}: {:?}",
            k.name,
            r.text().await
        );
        assert!(is_problem(&r), "{}: not problem+json", k.name);
        if k.status == 401 {
            assert!(r.headers().contains_key("www-authenticate"), "{}", k.name);
        }
        let p: Value = r.json().await.unwrap();
        assert_eq!(p["status"], k.status, "{}", k.name);
        assert!(
            p["type"].as_str().unwrap().starts_with("https://"),
            "{}",
            k.name
        );
        assert!(
            !p["title"].as_str().unwrap().is_empty() && !p["detail"].as_str().unwrap().is_empty()
        );
        if let Some(f) = k.field {
            assert_eq!(p["field"], f, "{}: {p}", k.name);
        }
    }
    assert_eq!(
        dump(&s.db).await,
        before,
        "hostile requests changed the database"
    );
    s.stop().await;
}

impl Case {
    fn with_path(mut self, p: &str) -> Self {
        self.path = p.to_owned();
        self
    }
}

#[tokio::test]
async fn a_body_over_the_limit_gets_413_and_changes_nothing() {
    let s = TestServer::start_with(|cfg| cfg.body_limit = 64 * 1024).await;
    let c = client();
    create_map(&c, &s, "hall").await;
    let before = dump(&s.db).await;
    let mut body = contribution(user_map(&world(1, 25), 5, 1.0, 0.1), "big");
    body["run"] = json!("x".repeat(100 * 1024));
    let r = post_contribution(&c, &s, "hall", ALICE, "big", &body).await;
    assert_eq!(r.status(), 413);
    assert!(is_problem(&r));
    assert_eq!(dump(&s.db).await, before);
    s.stop().await;
}
