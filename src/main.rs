fn main() {
    if let Err(e) = translucent_tof::cli::run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
