//! Pattern-family measurement operators (matrix-free).
