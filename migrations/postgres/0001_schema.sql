-- The PostgreSQL schema: the same tables as SQLite's migrations 0001-0004 (migrations/sqlite),
-- in PostgreSQL's types. Times are Unix milliseconds (BIGINT), taken from the database's clock
-- (helmholtz_now_ms) so that leases mean the same on every node, whatever its own clock says.

CREATE FUNCTION helmholtz_now_ms() RETURNS BIGINT
    LANGUAGE SQL VOLATILE
    AS $$ SELECT (EXTRACT(EPOCH FROM clock_timestamp()) * 1000)::BIGINT $$;

-- Sessions: a rig's declared patterns and detector layout, and how many rows are durable.
CREATE TABLE sessions (
    id              TEXT PRIMARY KEY NOT NULL,
    lab             TEXT NOT NULL,
    rig             TEXT NOT NULL,
    spec_json       TEXT NOT NULL,          -- canonical PatternSpec JSON
    channels_json   TEXT NOT NULL,          -- JSON array of channel names
    metadata_json   TEXT NOT NULL,          -- JSON object of strings
    directions_json TEXT NOT NULL DEFAULT '[]', -- [x, y, z] unit vectors toward the detectors
    camera_width    BIGINT,                 -- camera sessions: one frame per pattern
    camera_height   BIGINT,
    sample_format   TEXT NOT NULL DEFAULT 'f64' CHECK (sample_format IN ('f64', 'f32', 'u16')),
    expected_rows   BIGINT NOT NULL,
    committed_rows  BIGINT NOT NULL DEFAULT 0,
    state           TEXT NOT NULL DEFAULT 'open' CHECK (state IN ('open', 'finished')),
    gt_width        BIGINT,
    gt_height       BIGINT,
    gt_transport    BYTEA,                  -- f32 little-endian, row-major
    created_ms      BIGINT NOT NULL,
    finished_ms     BIGINT
);
CREATE INDEX sessions_lab ON sessions (lab, created_ms);

-- Rows, stored as the chunks they arrived in (after trimming any overlap). Chunks of a session
-- tile [0, committed_rows) exactly. Measurements do not compress: stored uncompressed, out of line.
CREATE TABLE measurement_chunks (
    session_id  TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    start_row   BIGINT NOT NULL,
    row_count   BIGINT NOT NULL CHECK (row_count > 0),
    data        BYTEA NOT NULL,             -- row-major rows x values, in the session's format
    PRIMARY KEY (session_id, start_row)
);
ALTER TABLE measurement_chunks ALTER COLUMN data SET STORAGE EXTERNAL;

-- The job queue: leases, heartbeats and fenced completion (every state write checks attempt).
CREATE TABLE jobs (
    id             BIGSERIAL PRIMARY KEY,
    kind           TEXT NOT NULL,
    lab            TEXT NOT NULL,
    state          TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
    priority       BIGINT NOT NULL DEFAULT 0,
    run_at_ms      BIGINT NOT NULL,
    attempt        BIGINT NOT NULL DEFAULT 0,
    max_attempts   BIGINT NOT NULL DEFAULT 3,
    lease_until_ms BIGINT,
    worker_id      TEXT,
    progress       DOUBLE PRECISION NOT NULL DEFAULT 0,
    last_error     TEXT,
    memory_bytes   BIGINT NOT NULL DEFAULT 0,
    created_ms     BIGINT NOT NULL,
    started_ms     BIGINT,
    finished_ms    BIGINT
);
CREATE INDEX jobs_claim ON jobs (state, priority DESC, run_at_ms, id);
CREATE INDEX jobs_lab_state ON jobs (lab, state);
CREATE INDEX jobs_lab_started ON jobs (lab, started_ms);

-- A reconstruction is a job of kind 'reconstruction' (same id) plus what it asked for and made.
CREATE TABLE reconstructions (
    id           BIGINT PRIMARY KEY REFERENCES jobs(id) ON DELETE CASCADE,
    session_id   TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    method       TEXT NOT NULL,
    params_json  TEXT NOT NULL,
    rows_used    BIGINT NOT NULL,
    report_json  TEXT,
    seconds      DOUBLE PRECISION
);
CREATE INDEX reconstructions_session ON reconstructions (session_id, id);

-- One dual image per detector channel of a finished reconstruction.
CREATE TABLE dual_images (
    reconstruction_id BIGINT NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    channel_index     BIGINT NOT NULL,
    channel_name      TEXT NOT NULL,
    width             BIGINT NOT NULL,
    height            BIGINT NOT NULL,
    data              BYTEA NOT NULL,       -- f32 little-endian, row-major
    PRIMARY KEY (reconstruction_id, channel_index)
);

-- A camera session's transport matrix T (TransportMatrix::encode), in parts 0, 1, ...
CREATE TABLE transports (
    reconstruction_id BIGINT NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    part              BIGINT NOT NULL,
    data              BYTEA NOT NULL,
    PRIMARY KEY (reconstruction_id, part)
);
ALTER TABLE transports ALTER COLUMN data SET STORAGE EXTERNAL;

-- Access tokens: only the SHA-256 of a token is stored.
CREATE TABLE tokens (
    id          BIGSERIAL PRIMARY KEY,
    lab         TEXT NOT NULL,
    roles       TEXT NOT NULL,              -- comma-separated subset of rig,reader,admin
    sha256      BYTEA NOT NULL UNIQUE CHECK (length(sha256) = 32),
    note        TEXT NOT NULL DEFAULT '',
    created_ms  BIGINT NOT NULL,
    revoked_ms  BIGINT                      -- NULL while the token is valid
);
CREATE INDEX tokens_lab ON tokens (lab, id);

-- One writer per session: the lease lives in the database, so the rule holds for every node.
CREATE TABLE upload_leases (
    session_id  TEXT PRIMARY KEY NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    holder      TEXT NOT NULL,
    writer      TEXT NOT NULL DEFAULT '',
    expires_ms  BIGINT NOT NULL
);
