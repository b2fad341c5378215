//! Image quality figures.
