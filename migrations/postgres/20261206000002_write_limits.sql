-- The write rate limit shared by every replica (GCRA): per contributor, the theoretical arrival
-- time of its next write, in ms since the epoch of the database's clock. A write is allowed when
-- that time lies at most the burst tolerance ahead of now; it then moves on by one emission
-- interval. One upsert per write, atomic under concurrent replicas.
CREATE TABLE write_limits (
    contributor TEXT PRIMARY KEY,
    tat_ms DOUBLE PRECISION NOT NULL
);
