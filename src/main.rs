/// Large blocks in mappings of their own (see `translucent_tof::alloc`).
#[global_allocator]
static ALLOCATOR: translucent_tof::alloc::LargeMapped = translucent_tof::alloc::LargeMapped;

fn main() {
    if let Err(e) = translucent_tof::cli::run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
