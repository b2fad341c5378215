-- Camera sessions and detector directions (issue 4).
-- A camera session stores one frame of camera_width x camera_height pixels per pattern, in its
-- sample format ('f32' or 'u16', little-endian); bucket sessions store f64 rows as before.
ALTER TABLE sessions ADD COLUMN camera_width INTEGER;
ALTER TABLE sessions ADD COLUMN camera_height INTEGER;
ALTER TABLE sessions ADD COLUMN sample_format TEXT NOT NULL DEFAULT 'f64' CHECK (sample_format IN ('f64', 'f32', 'u16'));
-- JSON array of [x, y, z] unit vectors toward each bucket detector, or [] when not declared.
ALTER TABLE sessions ADD COLUMN directions_json TEXT NOT NULL DEFAULT '[]';

-- A camera session's reconstructed transport matrix T (TransportMatrix::encode), split into
-- parts of at most 64 MiB (part 0, 1, ...) so no single blob nears SQLite's size limit.
CREATE TABLE transports (
    reconstruction_id INTEGER NOT NULL REFERENCES reconstructions(id) ON DELETE CASCADE,
    part              INTEGER NOT NULL,
    data              BLOB NOT NULL,
    PRIMARY KEY (reconstruction_id, part)
) WITHOUT ROWID;
