#[global_allocator]
static ALLOC: helmholtz_server::alloc::CountingAlloc = helmholtz_server::alloc::CountingAlloc;

fn main() {
    helmholtz_server::alloc::retain_freed_memory();
    helmholtz_server::bench::main()
}
