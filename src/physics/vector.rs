//! Which build of the hand-vectorised loops runs: the inversion's lanes
//! ([`super::inversion`]) and the window fits' sums ([`super::surface`]) each
//! have one built for AVX2, taken when the processor has it, and one built
//! for any processor, which gives the same numbers bit for bit. A process can
//! ask for the second everywhere ([`use_portable_code`]; the binary does when
//! `TTOF_PORTABLE=1`), to check that on a machine with AVX2.

use std::sync::atomic::{AtomicBool, Ordering};

static PORTABLE: AtomicBool = AtomicBool::new(false);

/// From now on, in this process, the loops built for any processor (`true`)
/// or, where the processor has it, those built for AVX2 (`false`, the default).
pub fn use_portable_code(portable: bool) {
    PORTABLE.store(portable, Ordering::Relaxed);
}

/// Whether the AVX2 builds run: the processor has AVX2 and the portable code
/// was not asked for.
#[inline]
pub fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        !PORTABLE.load(Ordering::Relaxed) && std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `avx2` or `portable`: which builds run ([`avx2`]).
pub fn name() -> &'static str {
    if avx2() {
        "avx2"
    } else {
        "portable"
    }
}
