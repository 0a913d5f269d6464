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

#[tokio::test]
async fn concurrent_uploads_lose_no_update() {
    let s = TestServer::start().await;
    let c = client();
    create_map(&c, &s, "crowd").await;
    let truth = world(3, 25);
    let tokens = [ALICE, BOB, OPERATOR, DAVE];
    let mut tasks = Vec::new();
    for u in 0..32u64 {
        let (c, url, truth) = (
            c.clone(),
            s.url("/v1/maps/crowd/contributions"),
            truth.clone(),
        );
        let token = tokens[(u % 4) as usize];
        let token = if token == DAVE { ALICE } else { token };
        tasks.push(tokio::spawn(async move {
            let mut out = Vec::new();
            for k in 0..10u64 {
                let body = contribution(
                    user_map(&truth, 1000 + u * 10 + k, 0.8, 0.1),
                    &format!("{u}-{k}"),
                );
                let r = c
                    .post(&url)
                    .bearer_auth(token)
                    .header("Idempotency-Key", format!("u{u}-k{k}"))
                    .json(&body)
                    .send()
                    .await
                    .unwrap();
                let status = r.status().as_u16();
                let v: Value = r.json().await.unwrap();
                out.push((status, v));
            }
            out
        }));
    }
    let mut accepted = Vec::new();
    let mut rejected = 0;
    for t in tasks {
        for (status, v) in t.await.unwrap() {
            assert!(status < 500, "{status}: {v}");
            match status {
                201 => accepted.push((
                    v["contribution"].as_i64().unwrap(),
                    v["version"].as_i64().unwrap(),
                )),
                422 => rejected += 1,
                other => panic!("unexpected {other}: {v}"),
            }
        }
    }
    assert_eq!(accepted.len() + rejected, 320);
    assert!(
        accepted.len() >= 300,
        "only {} of 320 accepted",
        accepted.len()
    );
    // versions 1..n without gaps, each produced by exactly one 201
    let mut versions: Vec<i64> = accepted.iter().map(|a| a.1).collect();
    versions.sort_unstable();
    assert_eq!(versions, (1..=accepted.len() as i64).collect::<Vec<_>>());
    let pool = sqlx::SqlitePool::connect_with(
        sqlx::sqlite::SqliteConnectOptions::new()
            .filename(&s.db)
            .read_only(true),
    )
    .await
    .unwrap();
    let provenance: Vec<(i64, i64)> =
        sqlx::query_as("SELECT contribution_id, number FROM versions ORDER BY number")
            .fetch_all(&pool)
            .await
            .unwrap();
    let mut expected = accepted.clone();
    expected.sort_by_key(|a| a.1);
    assert_eq!(
        provenance, expected,
        "every 201 in exactly one version's provenance"
    );
    let stored: Vec<(i64, String)> =
        sqlx::query_as("SELECT id, status FROM contributions ORDER BY id")
            .fetch_all(&pool)
            .await
            .unwrap();
    assert_eq!(stored.len(), 320);
    for (id, _) in &accepted {
        assert_eq!(
            stored
                .iter()
                .filter(|(i, st)| i == id && st == "accepted")
                .count(),
            1
        );
    }
    // parent chain
    let parents: Vec<(i64, Option<i64>)> =
        sqlx::query_as("SELECT number, parent FROM versions ORDER BY number")
            .fetch_all(&pool)
            .await
            .unwrap();
    for (n, p) in parents {
        assert_eq!(p, (n > 1).then_some(n - 1));
    }
    // Every version reads back as exactly the merge of its parent and its upload — whether
    // its body is stored whole or as a delta (group commits store all but their last version
    // as deltas; this load forms batches, so both kinds are read).
    let stored: Vec<(i64, String, String, String)> = sqlx::query_as(
        "SELECT v.number, v.encoding, c.body, c.request_sha256 FROM versions v
         JOIN contributions c ON c.id = v.contribution_id ORDER BY v.number",
    )
    .fetch_all(&pool)
    .await
    .unwrap();
    assert!(stored.iter().any(|v| v.1 == "delta") && stored.iter().any(|v| v.1 == "full"));
    let chain: Vec<(i64, String, String)> = stored
        .into_iter()
        .map(|(n, _, body, sha)| (n, body, sha))
        .collect();
    assert_versions_are_merges(&c, &[&s.base], "crowd", &chain).await;
    pool.close().await;
    let cur: Value = c
        .get(s.url("/v1/maps/crowd"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(cur["version"], accepted.len() as i64);
    assert_eq!(cur["contributions"], accepted.len() as i64);
    s.stop().await;
}

#[tokio::test]
async fn an_unrelated_map_is_rejected_and_rollback_equals_merging_the_others() {
    let s = TestServer::start().await;
    let c = client();
    let bodies = seeded_map(&c, &s, "r1").await;
    let before: Value = c
        .get(s.url("/v1/maps/r1"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    // poisoning: a random unrelated map
    for (i, seed) in [901u64, 902, 903].into_iter().enumerate() {
        let poison = contribution(user_map(&world(seed, 25), seed, 0.9, 0.1), "poison");
        let r = post_contribution(&c, &s, "r1", BOB, &format!("poison-{i}"), &poison).await;
        assert_eq!(r.status(), 422);
        assert!(is_problem(&r));
        let p: Value = r.json().await.unwrap();
        assert!(common::is_refusal(&p), "{p}");
        assert!(p["contribution"].as_i64().is_some());
    }
    let after: Value = c
        .get(s.url("/v1/maps/r1"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(after, before, "a rejected contribution changed the map");
    let page: Value = c
        .get(s.url("/v1/maps/r1/contributions"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let statuses: Vec<&str> = page["contributions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x["status"].as_str().unwrap())
        .collect();
    assert_eq!(
        statuses,
        [
            "accepted", "accepted", "accepted", "rejected", "rejected", "rejected"
        ]
    );

    // roll back the second contribution
    let second = page["contributions"][1]["id"].as_i64().unwrap();
    let r = c
        .delete(s.url(&format!("/v1/maps/r1/contributions/{second}")))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let rb: Value = r.json().await.unwrap();
    assert_eq!(rb["version"], 4);
    assert_eq!(rb["dropped"], json!([]));
    let again = c
        .delete(s.url(&format!("/v1/maps/r1/contributions/{second}")))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(again.status(), 409);
    let rolled: Value = c
        .get(s.url("/v1/maps/r1"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(rolled["version"], 4);
    assert_eq!(rolled["contributions"], 2);
    // history is kept
    let v2: Value = c
        .get(s.url("/v1/maps/r1/versions/2"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(v2["version"], 2);
    assert_eq!(v2["contributions"], 2);

    // the same uploads without the second, merged afresh into another map
    create_map(&c, &s, "r2").await;
    for (k, b) in bodies.iter().enumerate() {
        if k == 1 {
            continue;
        }
        let r = post_contribution(&c, &s, "r2", ALICE, &format!("r2-{k}"), b).await;
        assert_eq!(r.status(), 201);
    }
    let fresh: Value = c
        .get(s.url("/v1/maps/r2"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(rolled["transmitters"], fresh["transmitters"]);
    assert_ne!(rolled["transmitters"], before["transmitters"]);
    s.stop().await;
}

#[tokio::test]
async fn etag_changes_exactly_when_the_version_changes() {
    let s = TestServer::start().await;
    let c = client();
    create_map(&c, &s, "hall").await;
    let etag_of = |r: &reqwest::Response| r.headers()["etag"].to_str().unwrap().to_owned();
    let r = c.get(s.url("/v1/maps/hall")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let e0 = etag_of(&r);
    let v0: Value = r.json().await.unwrap();
    assert_eq!(v0["version"], 0);
    assert_eq!(v0["transmitters"], json!([]));
    let truth = world(1, 25);
    let mut last = e0.clone();
    for (k, seed) in [1u64, 2, 3].into_iter().enumerate() {
        let r = c
            .get(s.url("/v1/maps/hall"))
            .header("If-None-Match", &last)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 304);
        assert_eq!(etag_of(&r), last);
        assert!(r.bytes().await.unwrap().is_empty());
        let body = contribution(user_map(&truth, seed, 0.9, 0.1), "e");
        assert_eq!(
            post_contribution(&c, &s, "hall", ALICE, &format!("e{k}"), &body)
                .await
                .status(),
            201
        );
        let r = c
            .get(s.url("/v1/maps/hall"))
            .header("If-None-Match", &last)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let e = etag_of(&r);
        assert_ne!(e, last);
        let v: Value = r.json().await.unwrap();
        assert_eq!(e, format!("\"{}\"", v["version"]));
        last = e;
    }
    // a rejected contribution leaves the ETag alone
    let poison = contribution(user_map(&world(77, 25), 7, 0.9, 0.1), "p");
    assert_eq!(
        post_contribution(&c, &s, "hall", ALICE, "p", &poison)
            .await
            .status(),
        422
    );
    let r = c
        .get(s.url("/v1/maps/hall"))
        .header("If-None-Match", &last)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    let r = c
        .get(s.url("/v1/maps/hall"))
        .header("If-None-Match", "W/\"999\", *")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    s.stop().await;
}

fn resolve<'a>(doc: &'a Value, r: &str) -> Option<&'a Value> {
    let path = r.strip_prefix("#/")?;
    path.split('/').try_fold(doc, |v, k| v.get(k))
}

fn all_refs(v: &Value, out: &mut Vec<String>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                if k == "$ref" {
                    out.push(x.as_str().unwrap().to_owned());
                }
                all_refs(x, out);
            }
        }
        Value::Array(a) => a.iter().for_each(|x| all_refs(x, out)),
        _ => {}
    }
}

#[tokio::test]
async fn openapi_document_is_valid_and_lists_every_route() {
    let s = TestServer::start().await;
    let c = client();
    seeded_map(&c, &s, "hall").await;
    let doc: Value = c
        .get(s.url("/openapi.json"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    assert!(doc["info"]["title"].is_string() && doc["info"]["version"].is_string());
    let mut refs = Vec::new();
    all_refs(&doc, &mut refs);
    assert!(!refs.is_empty());
    for r in &refs {
        assert!(resolve(&doc, r).is_some(), "dangling $ref {r}");
    }
    let paths = doc["paths"].as_object().unwrap();
    let mut documented = Vec::new();
    for (path, item) in paths {
        for (method, op) in item.as_object().unwrap() {
            if !["get", "put", "post", "delete", "patch"].contains(&method.as_str()) {
                continue;
            }
            assert!(
                op["responses"].as_object().is_some_and(|r| !r.is_empty()),
                "{method} {path}"
            );
            documented.push(format!("{} {path}", method.to_uppercase()));
        }
    }
    documented.sort();
    let mut expected = vec![
        "GET /healthz",
        "GET /readyz",
        "GET /metrics",
        "GET /v1/maps",
        "PUT /v1/maps/{map}",
        "GET /v1/maps/{map}",
        "GET /v1/maps/{map}/versions/{n}",
        "POST /v1/maps/{map}/contributions",
        "POST /v1/maps/{map}/match",
        "GET /v1/maps/{map}/contributions",
        "DELETE /v1/maps/{map}/contributions/{id}",
    ];
    expected.sort();
    assert_eq!(documented, expected);
    // every documented operation is served (reaches its handler, not the 404 fallback / 405)
    for op in &documented {
        let (method, path) = op.split_once(' ').unwrap();
        let url = s.url(
            &path
                .replace("{map}", "hall")
                .replace("{n}", "1")
                .replace("{id}", "1"),
        );
        let r = c
            .request(method.parse().unwrap(), url)
            .bearer_auth(OPERATOR)
            .header("Idempotency-Key", "openapi-probe")
            .header("content-type", "application/json")
            .body("{}")
            .send()
            .await
            .unwrap();
        assert_ne!(r.status(), 405, "{op}");
        let text = r.text().await.unwrap();
        assert!(!text.contains("no such route"), "{op}: {text}");
    }
    let docs = c.get(s.url("/docs/")).send().await.unwrap();
    assert_eq!(docs.status(), 200);
    assert!(docs.text().await.unwrap().contains("swagger"));
    s.stop().await;
}

#[tokio::test]
async fn tokens_scopes_rate_limits_and_private_maps() {
    let s = TestServer::start_with(|cfg| {
        cfg.rate_limit_per_s = 1;
        cfg.rate_limit_burst = 3;
    })
    .await;
    let c = client();
    // the burst is 3 writes, the 4th is limited
    for name in ["a", "b", "c"] {
        let r = c
            .put(s.url(&format!("/v1/maps/{name}")))
            .bearer_auth(BOB)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
    }
    let r = c
        .put(s.url("/v1/maps/d"))
        .bearer_auth(BOB)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 429);
    assert!(
        r.headers()["retry-after"]
            .to_str()
            .unwrap()
            .parse::<u64>()
            .unwrap()
            >= 1
    );
    assert!(is_problem(&r));
    // another token has its own budget; idempotent create answers 200
    let r = c
        .put(s.url("/v1/maps/a"))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    // a private map
    let r = c
        .put(s.url("/v1/maps/secret"))
        .bearer_auth(ALICE)
        .json(&json!({"private": true}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let r = c
        .put(s.url("/v1/maps/secret"))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 409, "same name, other settings");
    let r = c.get(s.url("/v1/maps/secret")).send().await.unwrap();
    assert_eq!(r.status(), 401);
    assert!(
        r.headers()["www-authenticate"]
            .to_str()
            .unwrap()
            .starts_with("Bearer")
    );
    let r = c
        .get(s.url("/v1/maps/secret"))
        .bearer_auth(CAROL)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);
    let r = c
        .get(s.url("/v1/maps/secret"))
        .bearer_auth(OPERATOR)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let public: Value = c
        .get(s.url("/v1/maps"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let names: Vec<&str> = public["maps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["a", "b", "c"]);
    let all: Value = c
        .get(s.url("/v1/maps"))
        .bearer_auth(OPERATOR)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(all["maps"].as_array().unwrap().len(), 4);
    s.stop().await;
}

#[tokio::test]
async fn metrics_count_requests_merges_and_rejections() {
    let s = TestServer::start().await;
    let c = client();
    seeded_map(&c, &s, "metered").await;
    let poison = contribution(user_map(&world(55, 25), 5, 0.9, 0.1), "p");
    assert_eq!(
        post_contribution(&c, &s, "metered", ALICE, "m-p", &poison)
            .await
            .status(),
        422
    );
    let text = c
        .get(s.url("/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    for needle in [
        "http_requests_total{",
        "route=\"/v1/maps/{map}/contributions\"",
        "status=\"201\"",
        "status=\"422\"",
        "http_request_duration_seconds_bucket{",
        "echomap_merges_total",
        "echomap_rejections_total",
        "echomap_integrate_duration_seconds_bucket",
        "echomap_map_transmitters{map=\"metered\"}",
    ] {
        assert!(text.contains(needle), "missing {needle} in\n{text}");
    }
    s.stop().await;
}

#[tokio::test]
async fn match_endpoint_returns_the_agent_from_map_transform_and_writes_nothing() {
    let s = TestServer::start().await;
    let c = client();
    seeded_map(&c, &s, "hall").await;
    let before = dump(&s.db).await;
    let truth = world(1, 25);
    let partial = user_map(&truth, 4242, 0.5, 0.05);
    let r = c
        .post(s.url("/v1/maps/hall/match"))
        .json(&json!({"map": partial}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let m: Value = r.json().await.unwrap();
    assert_eq!(m["accepted"], true, "{m}");
    // agent_from_map ∘ map_from_agent = identity
    let t = |v: &Value| {
        (
            v["angle_rad"].as_f64().unwrap(),
            v["translation"][0].as_f64().unwrap(),
            v["translation"][1].as_f64().unwrap(),
        )
    };
    let (a1, x1, y1) = t(&m["agent_from_map"]);
    let (a2, x2, y2) = t(&m["map_from_agent"]);
    let (s1, c1) = a1.sin_cos();
    let (xc, yc) = (c1 * x2 - s1 * y2 + x1, s1 * x2 + c1 * y2 + y1);
    assert!(
        ((a1 + a2 + 3.0 * std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
            - std::f64::consts::PI)
            .abs()
            < 1e-9
    );
    assert!(xc.abs() < 1e-9 && yc.abs() < 1e-9);
    // correspondences pair views of the same world transmitter
    for p in m["correspondences"].as_array().unwrap() {
        let wa = p["agent"].as_str().unwrap().split('-').nth(1).unwrap();
        let wm = p["map"].as_str().unwrap().split('-').nth(1).unwrap();
        assert_eq!(wa, wm);
    }
    let unrelated = user_map(&world(31, 25), 1, 0.9, 0.1);
    let r = c
        .post(s.url("/v1/maps/hall/match"))
        .json(&json!({"map": unrelated}))
        .send()
        .await
        .unwrap();
    let m: Value = r.json().await.unwrap();
    assert_eq!(m["accepted"], false);
    assert!(m["reason"].is_string());
    assert_eq!(dump(&s.db).await, before);
    s.stop().await;
}

#[tokio::test]
async fn sqlite_settings_are_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("fresh.db");
    let storage = echomap_server::storage::Storage::open(&db.display().to_string(), 2)
        .await
        .unwrap();
    assert!(db.exists(), "the database file is created");
    for p in storage.pragmas().await.unwrap() {
        assert_eq!(p.journal_mode, "wal");
        assert_eq!(p.synchronous, 2, "synchronous=FULL");
        assert!(p.busy_timeout_ms >= 5000, "{}", p.busy_timeout_ms);
        assert_eq!(p.foreign_keys, 1);
    }
    assert!(storage.ready().await.unwrap());
    storage.close().await;
}

mod oneshot {
    //! Handler tests through `tower::ServiceExt::oneshot`, no socket.
    use axum::body::Body;
    use axum::http::{Request, StatusCode};
    use echomap_server::auth::TokenStore;
    use echomap_server::state::AppState;
    use echomap_server::{Config, routes, storage::Storage};
    use http_body_util::BodyExt;
    use std::sync::Arc;
    use tower::ServiceExt;

    async fn app() -> (axum::Router, tempfile::TempDir) {
        let dir = tempfile::tempdir().unwrap();
        let url = dir.path().join("h.db").display().to_string();
        let storage = Storage::open(&url, 1).await.unwrap();
        let tokens = TokenStore::parse("op-token-0123456789 op *\n").unwrap();
        let state = Arc::new(AppState::new(storage, tokens, Config::for_database(url)));
        (routes::app(state), dir)
    }

    #[tokio::test]
    async fn health_ready_and_fallback() {
        let (app, _dir) = app().await;
        let r = app
            .clone()
            .oneshot(Request::get("/healthz").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let r = app
            .clone()
            .oneshot(Request::get("/readyz").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let r = app
            .clone()
            .oneshot(Request::get("/v2/nothing").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::NOT_FOUND);
        assert_eq!(r.headers()["content-type"], "application/problem+json");
        let r = app
            .clone()
            .oneshot(Request::put("/v1/maps/x").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
        let r = app
            .oneshot(
                Request::put("/v1/maps/x")
                    .header("authorization", "Bearer op-token-0123456789")
                    .body(Body::empty())
                    .unwrap(),
            )
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::CREATED);
        let body: serde_json::Value =
            serde_json::from_slice(&r.into_body().collect().await.unwrap().to_bytes()).unwrap();
        assert_eq!(body["name"], "x");
        assert_eq!(body["version"], 0);
    }
}

#[tokio::test]
async fn merge_absorb_chi2_folds_an_uploads_second_copy_into_the_map() {
    let truth = world(1, 25);
    let first = contribution(user_map(&truth, 100, 1.0, 0.1), "a");
    // the second user mapped transmitter 0 twice (two tracks of it never associated)
    let mut second = user_map(&truth, 200, 1.0, 0.1);
    let txs = second["transmitters"].as_array_mut().unwrap();
    let mut copy = txs[0].clone();
    copy["id"] = json!("copy");
    let x = copy["components"][0]["mean"][0].as_f64().unwrap();
    copy["components"][0]["mean"][0] = json!(x + 0.05);
    txs.push(copy);
    let second = contribution(second, "b");
    for absorb in [0.0, 9.21] {
        let s = TestServer::start_with(|cfg| cfg.merge_absorb_chi2 = absorb).await;
        let c = client();
        create_map(&c, &s, "hall").await;
        let r = post_contribution(&c, &s, "hall", ALICE, "k-a", &first).await;
        assert_eq!(r.status(), 201);
        let r = post_contribution(&c, &s, "hall", BOB, "k-b", &second).await;
        assert_eq!(r.status(), 201);
        let rb: Value = r.json().await.unwrap();
        let cur: Value = c
            .get(s.url("/v1/maps/hall"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let ids: Vec<&str> = cur["transmitters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t["id"].as_str().unwrap())
            .collect();
        let (merged, added) = (
            rb["merged"].as_u64().unwrap(),
            rb["added"].as_u64().unwrap(),
        );
        assert_eq!(merged + added, 26, "{rb}");
        assert_eq!(ids.len() as u64, 25 + added, "{absorb}");
        if absorb == 0.0 {
            assert!(added >= 1, "{rb}");
            assert!(ids.contains(&"copy"));
        } else {
            assert_eq!(added, 0, "{rb}");
            assert!(!ids.contains(&"copy"));
        }
        s.stop().await;
    }
}

/// A dense field over the 60 m × 40 m area of `world`: two thirds of the transmitters with
/// b = 0, the rest with a clock offset of up to 30 m — the kind of map that coincides most
/// easily with another.
fn dense_field(seed: u64, n: usize) -> Vec<[f64; 3]> {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let b = if rng.random_bool(2.0 / 3.0) {
                0.0
            } else {
                rng.random_range(0.0..30.0)
            };
            [
                rng.random_range(-30.0..30.0),
                rng.random_range(-20.0..20.0),
                b,
            ]
        })
        .collect()
}

#[tokio::test]
async fn a_contributor_uploading_unrelated_maps_cannot_poison_the_map_or_fill_the_table() {
    let s = TestServer::start().await;
    let c = client();
    create_map(&c, &s, "city").await;
    let truth = world(1, 25);
    for (k, seed) in (21u64..26).enumerate() {
        let b = contribution(user_map(&truth, seed, 0.85, 0.1), &format!("run-{k}"));
        let r = post_contribution(&c, &s, "city", ALICE, &format!("good-{k}"), &b).await;
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    }
    let get_map = || async {
        c.get(s.url("/v1/maps/city"))
            .send()
            .await
            .unwrap()
            .json::<Value>()
            .await
            .unwrap()
    };
    let before = get_map().await;
    assert_eq!(before["version"], 5);
    let quota = echomap_server::config::defaults::REJECTED_QUOTA_PER_DAY as usize;
    let (mut unmatched, mut over_quota) = (0, 0);
    for i in 0..100u64 {
        // dense unrelated fields of 8–40 transmitters, 0.3 m noise, each a fresh run
        let n = 8 + (i as usize * 7) % 33;
        let poison = contribution(
            user_map(&dense_field(5000 + i, n), 7000 + i, 1.0, 0.3),
            &format!("poison-run-{i}"),
        );
        let r = post_contribution(&c, &s, "city", BOB, &format!("poison-{i}"), &poison).await;
        let status = r.status().as_u16();
        assert!(is_problem(&r), "upload {i}: not problem+json");
        let retry_after = r.headers().get("retry-after").cloned();
        let p: Value = r.json().await.unwrap();
        let detail = p["detail"].as_str().unwrap_or_default().to_owned();
        match status {
            422 => {
                unmatched += 1;
                let kind = p["type"].as_str().unwrap();
                assert!(
                    kind.ends_with("/unmatched") || kind.ends_with("/undecided"),
                    "{p}"
                );
                assert!(p["contribution"].as_i64().is_some(), "{p}");
                assert!(
                    detail.contains("inliers") || detail.contains("triple"),
                    "upload {i}: the refusal does not say why: {detail}"
                );
            }
            429 => {
                over_quota += 1;
                assert!(
                    p["type"].as_str().unwrap().ends_with("/quota-exceeded"),
                    "{p}"
                );
                assert!(detail.contains("quota"), "{detail}");
                assert!(retry_after.is_some(), "upload {i}: 429 without Retry-After");
            }
            other => panic!("upload {i}: unrelated map answered {other}: {p}"),
        }
    }
    assert_eq!(
        unmatched, quota,
        "every upload up to the quota is matched and refused"
    );
    assert_eq!(over_quota, 100 - quota);
    let after = get_map().await;
    assert_eq!(
        after["version"], before["version"],
        "a poisoned upload made a version"
    );
    assert_eq!(after["transmitters"], before["transmitters"]);
    // the table holds the good contributions and no more than the quota of refusals
    let page: Value = c
        .get(s.url("/v1/maps/city/contributions?limit=200"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let rows = page["contributions"].as_array().unwrap();
    let rejected = rows.iter().filter(|x| x["status"] == "rejected").count();
    assert_eq!(rows.len(), 5 + quota);
    assert_eq!(rejected, quota);
    // another contributor is not held back by the quota
    let b = contribution(user_map(&truth, 31, 0.85, 0.1), "alice-late");
    let r = post_contribution(&c, &s, "city", ALICE, "good-late", &b).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    s.stop().await;
}
