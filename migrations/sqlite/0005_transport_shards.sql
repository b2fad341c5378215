-- A camera session's transport matrix T solved in shards (issue 19): the worker holding the
-- transport job chooses the model once and stores it on the reconstruction (JSON,
-- helmholtz_recon::transport::TransportModel); the model's blocks of camera pixels are split
-- into shards that any worker sharing the database takes, leased, heart-beaten and fenced by
-- attempt like jobs. A shard's result is its encoded part (TransportPart::encode); the job's
-- holder assembles the parts in shard order into T.
ALTER TABLE reconstructions ADD COLUMN transport_model TEXT;

CREATE TABLE transport_shards (
    reconstruction_id INTEGER NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    shard             INTEGER NOT NULL,     -- 0, 1, ... in block order
    first_block       INTEGER NOT NULL,     -- the model's blocks first_block .. end_block - 1
    end_block         INTEGER NOT NULL CHECK (end_block > first_block),
    state             TEXT NOT NULL DEFAULT 'queued' CHECK (state IN ('queued', 'running', 'done', 'failed')),
    attempt           INTEGER NOT NULL DEFAULT 0,
    max_attempts      INTEGER NOT NULL DEFAULT 3,
    lease_until_ms    INTEGER,
    worker_id         TEXT,                 -- the worker of the latest attempt
    last_error        TEXT,
    part              BLOB,                 -- TransportPart::encode, once done
    created_ms        INTEGER NOT NULL,
    started_ms        INTEGER,
    finished_ms       INTEGER,
    PRIMARY KEY (reconstruction_id, shard)
);
CREATE INDEX transport_shards_claim ON transport_shards (state, reconstruction_id, shard);
