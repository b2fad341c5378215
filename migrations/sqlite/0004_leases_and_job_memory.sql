-- One writer per session (issue 17): an upload stream holds its session's lease while it is
-- open, renewed by heartbeats and by every append; an append checks, in its own transaction,
-- that its stream still holds the lease (fencing). A lease whose holder died expires, so the
-- next writer can take it. The lease lives in the database, so the rule holds for every server
-- process that shares it.
CREATE TABLE upload_leases (
    session_id  TEXT PRIMARY KEY NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    holder      TEXT NOT NULL,              -- the stream's id: process, time, counter
    writer      TEXT NOT NULL DEFAULT '',   -- the client's upload id (x-helmholtz-writer), if sent:
                                            -- its next stream takes over from a stale one
    expires_ms  INTEGER NOT NULL
) WITHOUT ROWID;

-- A job's estimated peak memory (bytes), made when it is requested: a worker claims it only
-- while its process's running jobs leave that much of the process's memory budget.
ALTER TABLE jobs ADD COLUMN memory_bytes INTEGER NOT NULL DEFAULT 0;
