//! What the generated OpenAPI document cannot say from the handlers' annotations alone, stated
//! once: the rules the server enforces on path and query parameters and on the map format
//! (patterns, bounds, fixed-size arrays), the identity fields of a served map version, and
//! every error status an operation can answer — each as `application/problem+json`.

use serde_json::{Value, json};

/// The statuses besides the success ones that an operation (`method`, `path` as in the
/// document) can answer, with what they mean.
fn errors_of(method: &str, path: &str) -> Vec<(&'static str, &'static str)> {
    // every operation that touches the database can meet an internal error or a database
    // that is not reachable
    let mut e = vec![
        ("500", "internal error (the cause is logged on the server)"),
        ("503", "the database is not reachable"),
    ];
    if !path.starts_with("/v1/") {
        return match path {
            "/readyz" => vec![(
                "503",
                "not ready: database unreachable or migrations missing",
            )],
            _ => Vec::new(),
        };
    }
    if path == "/v1/maps" {
        return e;
    }
    e.push((
        "400",
        "a malformed map name, id or query parameter (or body, for writes)",
    ));
    e.push(("401", "a token is needed (or the one given is unknown)"));
    e.push(("403", "the token may not read or write this map"));
    if method != "put" {
        e.push(("404", "no such map, version or contribution"));
    }
    let write = matches!(method, "put" | "post" | "delete");
    if write {
        e.push(("429", "rate limit or quota exceeded; see Retry-After"));
    }
    if matches!(method, "put" | "post") {
        e.push(("413", "request body too large"));
        e.push(("415", "the body is not application/json"));
        e.push((
            "422",
            "the body does not describe a valid request (the field is named)",
        ));
    }
    match (method, path) {
        ("put", _) => e.push(("409", "the map exists with other settings")),
        ("post", "/v1/maps/{map}/contributions") => e.push((
            "409",
            "an upload with the same Idempotency-Key is still in progress",
        )),
        ("delete", _) => e.push(("409", "not an accepted contribution")),
        _ => {}
    }
    e
}

fn problem() -> Value {
    json!({"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}})
}

fn parameter_schema(name: &str) -> Option<(Value, Option<&'static str>)> {
    Some(match name {
        "map" => (
            json!({"type": "string", "pattern": "^[a-z0-9._-]{1,64}$", "minLength": 1, "maxLength": 64,
                   "example": "floor1"}),
            Some("map name: 1–64 characters of [a-z0-9._-]"),
        ),
        "id" => (
            json!({"type": "integer", "format": "int64", "minimum": 1}),
            Some("contribution id"),
        ),
        "n" => (
            json!({"type": "integer", "format": "int64", "minimum": 1}),
            Some("version number"),
        ),
        "Idempotency-Key" => (
            json!({"type": "string", "pattern": "^[!-~]{1,255}$", "minLength": 1, "maxLength": 255}),
            Some("1–255 visible ASCII characters, unique per upload; a retry reuses it"),
        ),
        _ => return None,
    })
}

fn tighten_parameters(op: &mut Value) {
    let Some(params) = op.get_mut("parameters").and_then(Value::as_array_mut) else {
        return;
    };
    for p in params.iter_mut() {
        let name = p["name"].as_str().unwrap_or_default().to_owned();
        match name.as_str() {
            "after" => {
                p["in"] = json!("query");
                p["required"] = json!(false);
                p["schema"] =
                    json!({"type": "integer", "format": "int64", "minimum": 0, "default": 0});
            }
            "limit" => {
                p["in"] = json!("query");
                p["required"] = json!(false);
                p["schema"] = json!({"type": "integer", "format": "int64", "minimum": 1, "maximum": 1000, "default": 100});
            }
            _ => {
                if let Some((schema, description)) = parameter_schema(&name) {
                    p["schema"] = schema;
                    if let Some(d) = description {
                        p["description"] = json!(d);
                    }
                    p["required"] = json!(true);
                }
            }
        }
    }
}

/// Who may call an operation: writes need a bearer token; reads of public maps need none (a
/// private map's reads need a token allowed for it); the operational endpoints are open.
fn security_of(method: &str, path: &str) -> Value {
    if !path.starts_with("/v1/") {
        json!([])
    } else if matches!(method, "put" | "delete")
        || (method == "post" && path.ends_with("/contributions"))
    {
        json!([{"bearer": []}])
    } else {
        json!([{}, {"bearer": []}])
    }
}

fn tighten_responses(method: &str, path: &str, op: &mut Value) {
    let Some(responses) = op.get_mut("responses").and_then(Value::as_object_mut) else {
        return;
    };
    for (status, r) in responses.iter_mut() {
        if status.starts_with('4') || status.starts_with('5') {
            r["content"] = problem();
        }
    }
    for (status, description) in errors_of(method, path) {
        let r = responses
            .entry(status.to_owned())
            .or_insert_with(|| json!({"description": description}));
        r["content"] = problem();
        if r.get("description").is_none_or(|d| d == "") {
            r["description"] = json!(description);
        }
    }
}

/// The map format's rules, as `echomap_shared::map` validates them (what JSON Schema can say:
/// the weights' sum and positive definiteness cannot be, and stay in the descriptions).
fn tighten_map_schemas(schemas: &mut serde_json::Map<String, Value>) {
    let set =
        |schemas: &mut serde_json::Map<String, Value>, name: &str, field: &str, rule: Value| {
            if let Some(p) = schemas
                .get_mut(name)
                .and_then(|s| s.get_mut("properties"))
                .and_then(|p| p.get_mut(field))
                .and_then(Value::as_object_mut)
            {
                for (k, v) in rule.as_object().expect("an object") {
                    p.insert(k.clone(), v.clone());
                }
            }
        };
    set(
        schemas,
        "MapDoc",
        "format",
        json!({"enum": ["echomap.map.v1"]}),
    );
    set(
        schemas,
        "MapDoc",
        "hex_size_m",
        json!({"exclusiveMinimum": 0}),
    );
    set(
        schemas,
        "MapDoc",
        "transmitters",
        json!({"maxItems": echomap_shared::map::MAX_TRANSMITTERS}),
    );
    set(
        schemas,
        "TransmitterDoc",
        "id",
        json!({"minLength": 1, "maxLength": echomap_shared::map::MAX_ID_LEN}),
    );
    set(
        schemas,
        "TransmitterDoc",
        "components",
        json!({"minItems": 1, "maxItems": echomap_shared::map::MAX_COMPONENTS}),
    );
    set(
        schemas,
        "TransmitterDoc",
        "existence",
        json!({"minimum": 0, "maximum": 1}),
    );
    set(
        schemas,
        "TransmitterDoc",
        "reliability_m",
        json!({"minimum": 0}),
    );
    set(
        schemas,
        "ComponentDoc",
        "mean",
        json!({"minItems": 3, "maxItems": 3}),
    );
    set(
        schemas,
        "ComponentDoc",
        "cov",
        json!({"minItems": 3, "maxItems": 3,
               "items": {"type": "array", "items": {"type": "number", "format": "double"}, "minItems": 3, "maxItems": 3}}),
    );
    set(
        schemas,
        "ComponentDoc",
        "weight",
        json!({"exclusiveMinimum": 0, "maximum": 1}),
    );
    set(schemas, "CellDoc", "alpha", json!({"minimum": 0}));
    for axis in ["q", "r"] {
        set(
            schemas,
            "CellDoc",
            axis,
            json!({"minimum": i32::MIN, "maximum": i32::MAX}),
        );
    }
    // a contribution carries at least one transmitter
    if let Some(p) = schemas
        .get_mut("ContributionRequest")
        .and_then(|s| s.get_mut("properties"))
    {
        p["map"] = json!({
            "allOf": [{"$ref": "#/components/schemas/MapDoc"},
                      {"type": "object", "properties": {"transmitters": {"minItems": 1}}}],
            "description": "the user map, `echomap.map.v1`, in the agent's frame (at least one transmitter)"
        });
    }
    set(schemas, "CellDoc", "beta", json!({"minimum": 0}));
    // a served version is the map document with its identity beside it, in one object
    if let Some(doc) = schemas.get("MapDoc").cloned() {
        let mut version = doc;
        let props = version["properties"]
            .as_object_mut()
            .expect("MapDoc has properties");
        props.insert(
            "map".into(),
            json!({"type": "string", "description": "map name"}),
        );
        props.insert(
            "version".into(),
            json!({"type": "integer", "format": "int64", "minimum": 0,
                   "description": "version number, 1 for the first accepted contribution"}),
        );
        props.insert(
            "contributions".into(),
            json!({"type": "integer", "format": "int64", "minimum": 0,
                   "description": "accepted contributions merged into this version"}),
        );
        for f in ["map", "version", "contributions"] {
            version["required"]
                .as_array_mut()
                .expect("MapDoc has required fields")
                .push(json!(f));
        }
        version["description"] = json!(
            "A map version: the `echomap.map.v1` document in the map frame plus its identity."
        );
        schemas.insert("MapVersion".into(), version);
    }
}

/// OpenAPI links that chain the operations the way a client uses them (and a stateful tester
/// follows them): create a map → upload to it, read it, match against it; an upload → read the
/// version it made, roll it back.
fn add_links(paths: &mut serde_json::Map<String, Value>) {
    let mut link = |path: &str, method: &str, status: &str, links: Value| {
        if let Some(r) = paths
            .get_mut(path)
            .and_then(|i| i.get_mut(method))
            .and_then(|o| o.get_mut("responses"))
            .and_then(|r| r.get_mut(status))
        {
            r["links"] = links;
        }
    };
    let to_map = json!({
        "UploadToMap": {"operationId": "post_contribution", "parameters": {"map": "$response.body#/name"}},
        "ReadMap": {"operationId": "get_map", "parameters": {"map": "$response.body#/name"}},
        "MatchAgainstMap": {"operationId": "match_map", "parameters": {"map": "$response.body#/name"}},
        "ListContributions": {"operationId": "list_contributions", "parameters": {"map": "$response.body#/name"}}
    });
    link("/v1/maps/{map}", "put", "201", to_map.clone());
    link("/v1/maps/{map}", "put", "200", to_map);
    link(
        "/v1/maps/{map}/contributions",
        "post",
        "201",
        json!({
            "ReadVersion": {"operationId": "get_version",
                            "parameters": {"map": "$response.body#/map", "n": "$response.body#/version"}},
            "RollBack": {"operationId": "delete_contribution",
                         "parameters": {"map": "$response.body#/map", "id": "$response.body#/contribution"}}
        }),
    );
}

/// A valid map of five transmitters (agent frame), as an example of a request body.
fn example_map() -> Value {
    let txs: Vec<Value> = [
        [0.0, 0.0, 0.0],
        [12.0, 1.0, 0.0],
        [3.0, 9.0, 4.5],
        [-7.0, 5.0, 0.0],
        [6.0, -8.0, 2.0],
    ]
    .iter()
    .enumerate()
    .map(|(i, m)| {
        json!({"id": format!("t{}", i + 1), "existence": 0.95, "reliability_m": 40.0,
                   "components": [{"weight": 1.0, "mean": m,
                                   "cov": [[0.09, 0.0, 0.0], [0.0, 0.09, 0.0], [0.0, 0.0, 0.04]]}],
                   "visibility": [{"q": i, "r": 0, "alpha": 3.0, "beta": 1.0}]})
    })
    .collect();
    json!({"format": "echomap.map.v1", "hex_size_m": 2.0, "transmitters": txs})
}

fn add_examples(schemas: &mut serde_json::Map<String, Value>) {
    let mut example = |name: &str, value: Value| {
        if let Some(s) = schemas.get_mut(name) {
            s["examples"] = json!([value]);
        }
    };
    example(
        "ContributionRequest",
        json!({"contributor": "phone-7", "run": "walk-2026-12-05", "traveled_m": 152.3, "map": example_map()}),
    );
    example("MatchRequest", json!({"map": example_map()}));
    example("CreateMap", json!({"private": false}));
}

/// The document with the rules above applied (as JSON: some of them, e.g. a `$ref` narrowed by
/// `allOf`, are beyond utoipa's typed model).
pub fn tighten(doc: utoipa::openapi::OpenApi) -> Value {
    let mut v = serde_json::to_value(&doc).expect("the document serializes");
    if let Some(paths) = v.get_mut("paths").and_then(Value::as_object_mut) {
        for (path, item) in paths.iter_mut() {
            let Some(item) = item.as_object_mut() else {
                continue;
            };
            for (method, op) in item.iter_mut() {
                tighten_parameters(op);
                tighten_responses(method, path, op);
                op["security"] = security_of(method, path);
            }
        }
        add_links(paths);
    }
    v["components"]["securitySchemes"] = json!({
        "bearer": {"type": "http", "scheme": "bearer",
                   "description": "a token from the server's token file (`echomap-server --token-file`)"}
    });
    if let Some(schemas) = v
        .get_mut("components")
        .and_then(|c| c.get_mut("schemas"))
        .and_then(Value::as_object_mut)
    {
        tighten_map_schemas(schemas);
        add_examples(schemas);
    }
    v
}
