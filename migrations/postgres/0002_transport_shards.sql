-- A camera session's transport matrix T solved in shards (issue 19; the same tables as SQLite's
-- migration 0005): the worker holding the transport job chooses the model once and stores it on
-- the reconstruction (JSON, helmholtz_recon::transport::TransportModel); the model's blocks of
-- camera pixels are split into shards that any worker on any node takes (FOR UPDATE SKIP
-- LOCKED), leased on the database's clock, heart-beaten and fenced by attempt like jobs. A
-- shard's result is its encoded part (TransportPart::encode); the job's holder assembles the
-- parts in shard order into T.
ALTER TABLE reconstructions ADD COLUMN transport_model TEXT;

CREATE TABLE transport_shards (
    reconstruction_id BIGINT NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    shard             BIGINT NOT NULL,
    first_block       BIGINT NOT NULL,
    end_block         BIGINT NOT NULL CHECK (end_block > first_block),
    state             TEXT NOT NULL DEFAULT 'queued' CHECK (state IN ('queued', 'running', 'done', 'failed')),
    attempt           BIGINT NOT NULL DEFAULT 0,
    max_attempts      BIGINT NOT NULL DEFAULT 3,
    lease_until_ms    BIGINT,
    worker_id         TEXT,
    last_error        TEXT,
    part              BYTEA,
    created_ms        BIGINT NOT NULL,
    started_ms        BIGINT,
    finished_ms       BIGINT,
    PRIMARY KEY (reconstruction_id, shard)
);
ALTER TABLE transport_shards ALTER COLUMN part SET STORAGE EXTERNAL;
CREATE INDEX transport_shards_claim ON transport_shards (state, reconstruction_id, shard);
