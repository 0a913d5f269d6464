-- echomap map server schema for PostgreSQL (the scale path: several server replicas on one
-- database). The same tables, columns, constraints and indexes as the SQLite migrations in
-- the folder above (20261122000001_init.sql and 20261122000002_version_encoding.sql together),
-- in PostgreSQL's types: 64-bit integers everywhere (the server reads every integer as i64),
-- identity keys, BOOLEAN, DOUBLE PRECISION and BYTEA. Never edit after it lands: add a new
-- migration here and its SQLite twin in the folder above.

CREATE TABLE maps (
    id              BIGINT  GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    name            TEXT    NOT NULL UNIQUE,
    private         BOOLEAN NOT NULL DEFAULT FALSE,
    created_ms      BIGINT  NOT NULL,
    -- 0 until the first contribution is accepted
    current_version BIGINT  NOT NULL DEFAULT 0 CHECK (current_version >= 0)
);

CREATE TABLE contributions (
    id              BIGINT  GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    map_id          BIGINT  NOT NULL REFERENCES maps (id),
    contributor     TEXT    NOT NULL,          -- from the bearer token
    agent           TEXT,                      -- body "contributor": the device/agent label
    run             TEXT,                      -- body "run"
    traveled_m      DOUBLE PRECISION,
    idempotency_key TEXT    NOT NULL,
    request_sha256  TEXT    NOT NULL,          -- hash of the request body bytes
    body            TEXT    NOT NULL,          -- the upload verbatim
    received_ms     BIGINT  NOT NULL,
    status          TEXT    NOT NULL CHECK (status IN ('accepted', 'rejected', 'rolled_back')),
    reason          TEXT,
    transmitters    BIGINT  NOT NULL,
    matched_version BIGINT,                    -- version the upload was matched against
    transform       TEXT,                      -- JSON map_from_agent
    inliers         BIGINT,
    score           DOUBLE PRECISION,
    merged          BIGINT,
    added           BIGINT,
    response_status BIGINT  NOT NULL,          -- the stored response, replayed byte for byte
    response_body   BYTEA   NOT NULL,
    UNIQUE (map_id, contributor, idempotency_key)
);

CREATE INDEX contributions_by_map ON contributions (map_id, id);

CREATE TABLE versions (
    map_id          BIGINT  NOT NULL REFERENCES maps (id),
    number          BIGINT  NOT NULL CHECK (number >= 1),
    parent          BIGINT,                    -- previous version number, NULL for the first
    kind            TEXT    NOT NULL CHECK (kind IN ('merge', 'rollback')),
    contribution_id BIGINT  NOT NULL REFERENCES contributions (id),
    body            TEXT    NOT NULL,          -- the merged map (or a delta, see `encoding`)
    transmitters    BIGINT  NOT NULL,
    created_ms      BIGINT  NOT NULL,
    -- full: the echomap.map.v1 document; delta: only what the merge changed against the
    -- parent (server/src/delta.rs), resolved from the nearest earlier full body when read
    encoding        TEXT    NOT NULL DEFAULT 'full' CHECK (encoding IN ('full', 'delta')),
    PRIMARY KEY (map_id, number)
);

-- every accepted contribution is merged into exactly one version
CREATE UNIQUE INDEX versions_merge_provenance ON versions (contribution_id) WHERE kind = 'merge';
