-- echomap map server schema, version 1. Never edit after it lands: add a new migration.
-- Written in the SQL common to SQLite and PostgreSQL where possible; the PostgreSQL variant
-- will differ only in the auto-increment keys and BLOB → BYTEA.

CREATE TABLE maps (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    name            TEXT    NOT NULL UNIQUE,
    private         INTEGER NOT NULL DEFAULT 0 CHECK (private IN (0, 1)),
    created_ms      INTEGER NOT NULL,
    -- 0 until the first contribution is accepted
    current_version INTEGER NOT NULL DEFAULT 0 CHECK (current_version >= 0)
);

CREATE TABLE contributions (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    map_id          INTEGER NOT NULL REFERENCES maps (id),
    contributor     TEXT    NOT NULL,          -- from the bearer token
    agent           TEXT,                      -- body "contributor": the device/agent label
    run             TEXT,                      -- body "run"
    traveled_m      REAL,
    idempotency_key TEXT    NOT NULL,
    request_sha256  TEXT    NOT NULL,          -- hash of the request body bytes
    body            TEXT    NOT NULL,          -- the upload verbatim
    received_ms     INTEGER NOT NULL,
    status          TEXT    NOT NULL CHECK (status IN ('accepted', 'rejected', 'rolled_back')),
    reason          TEXT,
    transmitters    INTEGER NOT NULL,
    matched_version INTEGER,                   -- version the upload was matched against
    transform       TEXT,                      -- JSON map_from_agent
    inliers         INTEGER,
    score           REAL,
    merged          INTEGER,
    added           INTEGER,
    response_status INTEGER NOT NULL,          -- the stored response, replayed byte for byte
    response_body   BLOB    NOT NULL,
    UNIQUE (map_id, contributor, idempotency_key)
);

CREATE INDEX contributions_by_map ON contributions (map_id, id);

CREATE TABLE versions (
    map_id          INTEGER NOT NULL REFERENCES maps (id),
    number          INTEGER NOT NULL CHECK (number >= 1),
    parent          INTEGER,                   -- previous version number, NULL for the first
    kind            TEXT    NOT NULL CHECK (kind IN ('merge', 'rollback')),
    contribution_id INTEGER NOT NULL REFERENCES contributions (id),
    body            TEXT    NOT NULL,          -- the merged map, echomap.map.v1
    transmitters    INTEGER NOT NULL,
    created_ms      INTEGER NOT NULL,
    PRIMARY KEY (map_id, number)
);

-- every accepted contribution is merged into exactly one version
CREATE UNIQUE INDEX versions_merge_provenance ON versions (contribution_id) WHERE kind = 'merge';
