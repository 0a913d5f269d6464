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
