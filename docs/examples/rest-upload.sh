#!/bin/sh
# Upload a rig's rows with curl alone (no gRPC, no Helmholtz client): create a session, PUT the
# rows, finish. ROWS is a file of little-endian float64 bucket values, one per pattern (one
# channel), in pattern order. tests/tests/rest_upload.rs runs this script as it is.
#
#   HELMHOLTZ_SERVER=http://127.0.0.1:8080 HELMHOLTZ_TOKEN=hz_... sh rest-upload.sh ROWS [SESSION_ID]
set -eu
server=${HELMHOLTZ_SERVER:-http://127.0.0.1:8080}
: "${HELMHOLTZ_TOKEN:?set HELMHOLTZ_TOKEN to a token with the rig role}"
rows=${1:?usage: rest-upload.sh ROWS [SESSION_ID]}
id=${2:-curl-run-1}
auth="Authorization: Bearer $HELMHOLTZ_TOKEN"

# 1. The session: a complete 8 x 8 Hadamard set (64 split pairs = 128 patterns), one detector.
#    Creating it again with the same declaration is harmless (200 instead of 201).
curl -fsS -X POST -H "$auth" -H 'Content-Type: application/json' \
  -d '{"id": "'"$id"'", "rig": "curl-bench",
       "patterns": {"family": "hadamard", "width": 8, "height": 8, "count": 128, "seed": 0},
       "channels": ["bucket"]}' \
  "$server/v1/sessions" >/dev/null

# 2. The rows from row 0. Sending them again is harmless: rows the server already has are
#    compared byte for byte (rows_skipped), never stored twice. The body's SHA-256 goes in
#    Content-Digest (RFC 9530); x-helmholtz-crc32c with its CRC-32C works too.
digest=$(openssl dgst -sha256 -binary "$rows" | base64 | tr -d '\n')
curl -fsS -X PUT -H "$auth" -H 'Content-Type: application/octet-stream' \
  -H "Content-Digest: sha-256=:$digest:" --data-binary @"$rows" \
  "$server/v1/sessions/$id/rows?start_row=0"
echo

# 3. No more rows.
curl -fsS -X POST -H "$auth" "$server/v1/sessions/$id/finish" >/dev/null
