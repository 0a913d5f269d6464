-- Version bodies may be stored as deltas against their parent (server/src/delta.rs): inside a
-- group commit every version but the last stores only the transmitters its merge changed.
-- Readers resolve a delta from the nearest earlier full body. Existing rows are full bodies.
ALTER TABLE versions ADD COLUMN encoding TEXT NOT NULL DEFAULT 'full' CHECK (encoding IN ('full', 'delta'));
