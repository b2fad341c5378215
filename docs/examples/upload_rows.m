function result = upload_rows(server, token, session_id, start_row, rows)
%UPLOAD_ROWS  Send bucket rows to a Helmholtz session over REST (no gRPC needed).
%   result = upload_rows('http://127.0.0.1:8080', 'hz_...', 'run-1', 0, rows)
%   ROWS is a (patterns x channels) double matrix in pattern order; START_ROW the index of its
%   first row (the session's committed_rows to resume). RESULT holds committed_rows,
%   rows_written and rows_skipped. The body is raw little-endian float64, row-major, with its
%   CRC-32C in the x-helmholtz-crc32c header; the server refuses it whole (nothing stored) on a
%   bad checksum, a shape that is not whole rows, a non-finite value, rows that differ from
%   stored ones, or another writer. Untested here (no MATLAB on the build machines): the same
%   request is made by docs/examples/rest-upload.sh and tests/tests/rest_upload.rs.
    body = typecast(reshape(double(rows).', 1, []), 'uint8');   % row-major, little-endian
    crc = crc32c(body);
    url = sprintf('%s/v1/sessions/%s/rows?start_row=%d', server, session_id, start_row);
    options = weboptions('RequestMethod', 'put', 'MediaType', 'application/octet-stream', ...
        'HeaderFields', {'Authorization', ['Bearer ' token]; ...
                         'x-helmholtz-crc32c', lower(dec2hex(crc, 8))}, ...
        'ContentType', 'json', 'Timeout', 60);
    result = webwrite(url, body, options);
end

function crc = crc32c(bytes)
%CRC32C  CRC-32C (Castagnoli, reflected polynomial 0x82F63B78) of a uint8 vector.
    persistent table
    if isempty(table)
        table = zeros(1, 256, 'uint32');
        for n = 0:255
            c = uint32(n);
            for k = 1:8
                if bitand(c, 1)
                    c = bitxor(bitshift(c, -1), uint32(hex2dec('82F63B78')));
                else
                    c = bitshift(c, -1);
                end
            end
            table(n + 1) = c;
        end
    end
    crc = uint32(hex2dec('FFFFFFFF'));
    for b = bytes(:).'
        crc = bitxor(table(bitand(bitxor(crc, uint32(b)), 255) + 1), bitshift(crc, -8));
    end
    crc = bitxor(crc, uint32(hex2dec('FFFFFFFF')));
end
