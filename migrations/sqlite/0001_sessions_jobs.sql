-- Sessions: a rig's declared patterns and detector layout, and how many rows are durable.
CREATE TABLE sessions (
    id              TEXT PRIMARY KEY NOT NULL,
    rig             TEXT NOT NULL,
    spec_json       TEXT NOT NULL,          -- canonical PatternSpec JSON
    channels_json   TEXT NOT NULL,          -- JSON array of channel names
    metadata_json   TEXT NOT NULL,          -- JSON object of strings
    expected_rows   INTEGER NOT NULL,
    committed_rows  INTEGER NOT NULL DEFAULT 0,
    state           TEXT NOT NULL DEFAULT 'open' CHECK (state IN ('open', 'finished')),
    gt_width        INTEGER,
    gt_height       INTEGER,
    gt_transport    BLOB,                   -- f32 little-endian, row-major
    created_ms      INTEGER NOT NULL,
    finished_ms     INTEGER
);

-- Bucket rows, stored as the chunks they arrived in (after trimming any overlap).
-- Chunks of a session tile [0, committed_rows) exactly: start_row of each = end of the previous.
CREATE TABLE measurement_chunks (
    session_id  TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    start_row   INTEGER NOT NULL,
    row_count   INTEGER NOT NULL CHECK (row_count > 0),
    data        BLOB NOT NULL,              -- row-major rows x channels, f64 little-endian
    PRIMARY KEY (session_id, start_row)
) WITHOUT ROWID;

-- The job queue: leases, heartbeats and fenced completion (every state write checks attempt).
CREATE TABLE jobs (
    id            INTEGER PRIMARY KEY AUTOINCREMENT,
    kind          TEXT NOT NULL,
    state         TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
    priority      INTEGER NOT NULL DEFAULT 0,
    run_at_ms     INTEGER NOT NULL,
    attempt       INTEGER NOT NULL DEFAULT 0,
    max_attempts  INTEGER NOT NULL DEFAULT 3,
    lease_until_ms INTEGER,
    worker_id     TEXT,
    progress      REAL NOT NULL DEFAULT 0,
    last_error    TEXT,
    created_ms    INTEGER NOT NULL,
    started_ms    INTEGER,
    finished_ms   INTEGER
);
CREATE INDEX jobs_claim ON jobs (state, priority DESC, run_at_ms, id);

-- A reconstruction is a job of kind 'reconstruction' (same id) plus what it asked for and made.
CREATE TABLE reconstructions (
    id           INTEGER PRIMARY KEY REFERENCES jobs(id) ON DELETE CASCADE,
    session_id   TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    method       TEXT NOT NULL,
    params_json  TEXT NOT NULL,
    rows_used    INTEGER NOT NULL,
    report_json  TEXT,
    seconds      REAL
);
CREATE INDEX reconstructions_session ON reconstructions (session_id, id);

-- One dual image per detector channel of a finished reconstruction.
CREATE TABLE dual_images (
    reconstruction_id INTEGER NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    channel_index     INTEGER NOT NULL,
    channel_name      TEXT NOT NULL,
    width             INTEGER NOT NULL,
    height            INTEGER NOT NULL,
    data              BLOB NOT NULL,        -- f32 little-endian, row-major
    PRIMARY KEY (reconstruction_id, channel_index)
) WITHOUT ROWID;
