//! Fast Walsh-Hadamard transform.
