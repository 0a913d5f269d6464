-- Every move of a map's current version is announced on the channel `echomap_heads`, payload
-- `<map id>:<version>`. PostgreSQL delivers a notification when its transaction commits, to every
-- session listening then. Replicas started with `--replica-cache listen` keep serving their cached
-- current version until such a notification says the head moved, instead of reading the head on
-- every GET.
CREATE FUNCTION echomap_notify_head() RETURNS trigger AS $$
BEGIN
    PERFORM pg_notify('echomap_heads', NEW.id::text || ':' || NEW.current_version::text);
    RETURN NEW;
END;
$$ LANGUAGE plpgsql;

CREATE TRIGGER maps_head_moved
    AFTER UPDATE OF current_version ON maps
    FOR EACH ROW
    WHEN (OLD.current_version IS DISTINCT FROM NEW.current_version)
    EXECUTE FUNCTION echomap_notify_head();
