//! Solvers: FISTA, primal-dual TV, CG, Hadamard level inverses.
