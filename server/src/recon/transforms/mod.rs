//! Sparsifying transforms and total variation.
