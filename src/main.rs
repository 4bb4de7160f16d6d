/// Large blocks in mappings of their own (see `translucent_tof::alloc`).
#[global_allocator]
static ALLOCATOR: translucent_tof::alloc::LargeMapped = translucent_tof::alloc::LargeMapped;

fn main() {
    translucent_tof::alloc::keep_heap_tops();
    // The loops built for any processor even where AVX2 is at hand (the same numbers; a check).
    if std::env::var_os("TTOF_PORTABLE").is_some_and(|v| !v.is_empty() && v != "0") {
        translucent_tof::physics::vector::use_portable_code(true);
        eprintln!("TTOF_PORTABLE: the loops built for any processor run (not AVX2)");
    }
    if let Err(e) = translucent_tof::cli::run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
