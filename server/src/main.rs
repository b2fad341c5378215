fn main() { helmholtz_server::cli::main() }
