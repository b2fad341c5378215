-- Adaptive acquisition (issue 24; the same tables as SQLite's migration 0006): the server
-- chooses an adaptive session's patterns in batches of basis indices from the values measured
-- so far. Every batch is stored here before it is sent to the rig; `issued_rows` (twice the
-- pairs of every batch issued) bounds the rows an adaptive session accepts, checked under the
-- session's row lock in each append. NULL for the other families.
ALTER TABLE sessions ADD COLUMN issued_rows BIGINT;

CREATE TABLE adaptive_batches (
    session_id  TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    number      BIGINT NOT NULL,
    first_row   BIGINT NOT NULL,
    pairs       BIGINT NOT NULL CHECK (pairs > 0),
    indices     BYTEA NOT NULL,
    issued_ms   BIGINT NOT NULL,
    PRIMARY KEY (session_id, number)
);
