-- The per-contributor quota of rejected contributions counts a contributor's rejections of the
-- last 24 hours on every upload.
CREATE INDEX contributions_by_contributor ON contributions (contributor, received_ms);
