-- Labs and access tokens. A token belongs to one lab and carries one or more roles:
--   rig    create sessions and upload to them,
--   reader read the lab's sessions, reconstructions and images; request and cancel reconstructions,
--   admin  manage the lab's tokens.
-- Only the SHA-256 of a token is stored (tokens are 256-bit random secrets, printed once).
CREATE TABLE tokens (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    lab         TEXT NOT NULL,
    roles       TEXT NOT NULL,              -- comma-separated subset of rig,reader,admin
    sha256      BLOB NOT NULL UNIQUE CHECK (length(sha256) = 32),
    note        TEXT NOT NULL DEFAULT '',
    created_ms  INTEGER NOT NULL,
    revoked_ms  INTEGER                     -- NULL while the token is valid
);
CREATE INDEX tokens_lab ON tokens (lab, id);

-- Every session belongs to a lab; sessions from before labs existed belong to 'default'
-- (reach them with a token of lab 'default'), except the demo's own two sessions, which move to
-- lab 'demo' so that `helmholtz-server demo` stays idempotent on an existing data directory.
ALTER TABLE sessions ADD COLUMN lab TEXT NOT NULL DEFAULT 'default';
UPDATE sessions SET lab = 'demo' WHERE id IN ('demo-usaf-hadamard', 'demo-double-slit-dgi');
CREATE INDEX sessions_lab ON sessions (lab, created_ms);

-- The job queue is fair across labs: a job carries its lab so claims can balance them.
ALTER TABLE jobs ADD COLUMN lab TEXT NOT NULL DEFAULT 'default';
UPDATE jobs SET lab = COALESCE((SELECT s.lab FROM reconstructions r JOIN sessions s ON s.id = r.session_id
                                WHERE r.id = jobs.id), 'default');
CREATE INDEX jobs_lab_state ON jobs (lab, state);
CREATE INDEX jobs_lab_started ON jobs (lab, started_ms);
