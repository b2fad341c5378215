-- Adaptive acquisition (issue 24): the server chooses an adaptive session's patterns in batches
-- of basis indices from the values measured so far. Every batch is stored here before it is
-- sent to the rig; `issued_rows` (twice the pairs of every batch issued) bounds the rows an
-- adaptive session accepts, in the same transaction as each append. NULL for the other
-- families, whose rows are bounded by the spec's count alone.
ALTER TABLE sessions ADD COLUMN issued_rows INTEGER;

CREATE TABLE adaptive_batches (
    session_id  TEXT NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
    number      INTEGER NOT NULL,       -- 0, 1, ... in issue order
    first_row   INTEGER NOT NULL,       -- the batch's first frame: the previous batch's end
    pairs       INTEGER NOT NULL CHECK (pairs > 0),
    indices     BLOB NOT NULL,          -- one little-endian u32 basis index per pair
    issued_ms   INTEGER NOT NULL,
    PRIMARY KEY (session_id, number)
);
