#[global_allocator]
static ALLOC: helmholtz_alloc::CountingAlloc = helmholtz_alloc::CountingAlloc;

fn main() {
    helmholtz_alloc::retain_freed_memory();
    helmholtz_bench::main()
}
