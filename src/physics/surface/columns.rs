//! The inverse-depth fits' points held four to a group, field by field, and
//! the three sums their robust passes repeat: the weighted moments (the
//! normal equations), every point's residual with their sum of squares, and
//! the points a pass drops (taken out of the moments).
//!
//! Each is written once over a group of four lanes ([`Quad`]) and built
//! twice: with AVX2 where the processor has it (chosen at run time; each
//! group one vector register) and for any processor (four `f64`). Both do the
//! same operations in the same order, lane by lane, so they give the same
//! fits bit for bit (test `the_same_with_and_without_avx2`). Sums run in four
//! partial sums, one per lane, added `(l0 + l1) + (l2 + l3)` at the end.

use super::{Moments, RayPoint};

/// The points of a fit, four to a [`Group`]; the last group is padded with
/// points of weight 0 that are not kept.
#[derive(Default)]
pub(super) struct Columns {
    groups: Vec<Group>,
}

/// Four points' lanes: the image coordinates relative to the fit's centre,
/// the depth, the weight `w = z^4` (residuals in millimetres of z), the
/// right-hand side `w / z`, whether kept, the last residual.
#[derive(Clone, Copy)]
struct Group {
    a: [f64; 4],
    b: [f64; 4],
    z: [f64; 4],
    w: [f64; 4],
    rhs: [f64; 4],
    /// All ones for a kept point, 0 for one dropped (or padding).
    keep: [u64; 4],
    resid: [f64; 4],
}

/// At the centre, on the plane z = 1, weight 0: a padding point (a finite residual, never kept).
const PADDING: Group = Group {
    a: [0.0; 4],
    b: [0.0; 4],
    z: [1.0; 4],
    w: [0.0; 4],
    rhs: [0.0; 4],
    keep: [0; 4],
    resid: [0.0; 4],
};

const KEPT: u64 = u64::MAX;

impl Group {
    /// Lane `k` holds `p`, kept.
    #[inline(always)]
    fn set(&mut self, k: usize, p: &RayPoint, (a0, b0): (f64, f64)) {
        let z2 = p.z * p.z;
        self.a[k] = p.a - a0;
        self.b[k] = p.b - b0;
        self.z[k] = p.z;
        self.w[k] = z2 * z2; // d(1/z) = dz / z^2
        self.rhs[k] = z2 * p.z; // w / z
        self.keep[k] = KEPT;
    }
}

impl Columns {
    /// Holds `points` relative to `(a0, b0)`, every one kept.
    pub(super) fn fill(&mut self, points: &[RayPoint], (a0, b0): (f64, f64)) {
        // Every lane is written but the last group's padding, which is set first.
        self.groups.resize(points.len().div_ceil(4), PADDING);
        if let Some(last) = self.groups.last_mut() {
            *last = PADDING;
        }
        let mut four = points.chunks_exact(4);
        for (g, four) in self.groups.iter_mut().zip(&mut four) {
            for (k, p) in four.iter().enumerate() {
                g.set(k, p, (a0, b0));
            }
        }
        if let Some(g) = self.groups.last_mut() {
            for (k, p) in four.remainder().iter().enumerate() {
                g.set(k, p, (a0, b0));
            }
        }
    }

    /// The moments of every point held (all kept): those of degree up to 2,
    /// and up to 4 when `quartic` (a quadric's normal equations).
    pub(super) fn moments(&self, quartic: bool) -> Moments {
        #[cfg(target_arch = "x86_64")]
        if avx2() {
            // SAFETY: the processor has AVX2 (`avx2` checks it).
            return unsafe { avx::moments(self, quartic) };
        }
        // SAFETY: the portable lanes need no processor feature.
        unsafe { moments::<[f64; 4]>(self, quartic) }
    }

    /// Every point's residual `|z - 1 / fit|`, millimetres of z, for the
    /// polynomial `c` (see [`super::polynomial`]); the sum of the kept ones' squares.
    pub(super) fn residuals<const N: usize>(&mut self, c: &[f64; N]) -> f64 {
        #[cfg(target_arch = "x86_64")]
        if avx2() {
            // SAFETY: as in `moments`.
            return unsafe { avx::residuals(self, c) };
        }
        // SAFETY: as in `moments`.
        unsafe { residuals::<[f64; 4], N>(self, c) }
    }

    /// Drops the kept points whose residual is above `cut`, in order, taking
    /// each out of `moments`; how many.
    pub(super) fn drop_beyond(&mut self, cut: f64, moments: &mut Moments) -> usize {
        #[cfg(target_arch = "x86_64")]
        if avx2() {
            // SAFETY: as in `moments`.
            return unsafe { avx::drop_beyond(self, cut, moments) };
        }
        // SAFETY: as in `moments`.
        unsafe { drop_beyond::<[f64; 4]>(self, cut, moments) }
    }
}

#[cfg(target_arch = "x86_64")]
#[inline]
fn avx2() -> bool {
    #[cfg(test)]
    if FORCE_PORTABLE.with(|f| f.get()) {
        return false;
    }
    crate::physics::vector::avx2()
}

#[cfg(test)]
thread_local! {
    /// Tests set it to run the code built for any processor on this thread
    /// (see also [`crate::physics::vector::use_portable_code`], for the process).
    static FORCE_PORTABLE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` on this thread with the code built for any processor, whatever this one has.
#[cfg(test)]
pub(super) fn portable<T>(f: impl FnOnce() -> T) -> T {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            FORCE_PORTABLE.with(|p| p.set(self.0));
        }
    }
    let _restore = Restore(FORCE_PORTABLE.with(|p| p.replace(true)));
    f()
}

/// Four lanes of `f64`: the operations the sums need.
trait Quad: Copy {
    fn splat(v: f64) -> Self;
    fn load(s: &[f64; 4]) -> Self;
    /// Each all ones or 0, as a mask for [`Quad::and`].
    fn load_mask(s: &[u64; 4]) -> Self;
    fn store(self, s: &mut [f64; 4]);
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    fn abs(self) -> Self;
    /// Bitwise and: `self` where `mask` is all ones, 0 where it is 0.
    fn and(self, mask: Self) -> Self;
    /// Bit `k` set where lane `k` is above `v` (false for NaN) and `mask` is all ones.
    fn above_where(self, v: Self, mask: Self) -> u32;
    /// `(l0 + l1) + (l2 + l3)`.
    fn sum(self) -> f64;
}

impl Quad for [f64; 4] {
    #[inline(always)]
    fn splat(v: f64) -> Self {
        [v; 4]
    }
    #[inline(always)]
    fn load(s: &[f64; 4]) -> Self {
        *s
    }
    #[inline(always)]
    fn load_mask(s: &[u64; 4]) -> Self {
        s.map(f64::from_bits)
    }
    #[inline(always)]
    fn store(self, s: &mut [f64; 4]) {
        *s = self;
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        [0, 1, 2, 3].map(|k| self[k] + o[k])
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        [0, 1, 2, 3].map(|k| self[k] - o[k])
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        [0, 1, 2, 3].map(|k| self[k] * o[k])
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        [0, 1, 2, 3].map(|k| self[k] / o[k])
    }
    #[inline(always)]
    fn abs(self) -> Self {
        self.map(f64::abs)
    }
    #[inline(always)]
    fn and(self, mask: Self) -> Self {
        [0, 1, 2, 3].map(|k| f64::from_bits(self[k].to_bits() & mask[k].to_bits()))
    }
    #[inline(always)]
    fn above_where(self, v: Self, mask: Self) -> u32 {
        (0..4).fold(0, |m, k| m | (u32::from(self[k] > v[k] && mask[k].to_bits() != 0) << k))
    }
    #[inline(always)]
    fn sum(self) -> f64 {
        (self[0] + self[1]) + (self[2] + self[3])
    }
}

/// The moments: one sweep per family of sums, so each sweep's partial sums
/// stay in registers.
///
/// # Safety
///
/// With `Q` a vector register type (`__m256d`), the processor must have its
/// instructions (AVX); `[f64; 4]` needs nothing.
#[inline(always)]
unsafe fn moments<Q: Quad>(cols: &Columns, quartic: bool) -> Moments {
    let mut m = Moments::default();
    // `sum w a^p b^q`, p + q <= 2, and `sum (w / z) a^p b^q`.
    let mut s = [Q::splat(0.0); 6];
    let mut r = [Q::splat(0.0); 6];
    for g in &cols.groups {
        let (a, b, w) = (Q::load(&g.a), Q::load(&g.b), Q::load(&g.w));
        let (wa, wb) = (w.mul(a), w.mul(b));
        let t = [w, wa, wb, wa.mul(a), wa.mul(b), wb.mul(b)];
        for k in 0..6 {
            s[k] = s[k].add(t[k]);
        }
    }
    for g in &cols.groups {
        let (a, b, rhs) = (Q::load(&g.a), Q::load(&g.b), Q::load(&g.rhs));
        let (ra, rb) = (rhs.mul(a), rhs.mul(b));
        let t = [rhs, ra, rb, ra.mul(a), ra.mul(b), rb.mul(b)];
        for k in 0..6 {
            r[k] = r[k].add(t[k]);
        }
    }
    for k in 0..6 {
        m.w[k] = s[k].sum();
        m.rhs[k] = r[k].sum();
    }
    if quartic {
        let mut s = [Q::splat(0.0); 9];
        for g in &cols.groups {
            let (a, b, w) = (Q::load(&g.a), Q::load(&g.b), Q::load(&g.w));
            let (wa, wb) = (w.mul(a), w.mul(b));
            let (wa2, wab, wb2) = (wa.mul(a), wa.mul(b), wb.mul(b));
            let (wa3, wa2b, wab2, wb3) = (wa2.mul(a), wa2.mul(b), wab.mul(b), wb2.mul(b));
            let t = [
                wa3,
                wa2b,
                wab2,
                wb3,
                wa3.mul(a),
                wa3.mul(b),
                wa2b.mul(b),
                wab2.mul(b),
                wb3.mul(b),
            ];
            for k in 0..9 {
                s[k] = s[k].add(t[k]);
            }
        }
        for k in 0..9 {
            m.w[6 + k] = s[k].sum();
        }
    }
    m
}

/// See [`Columns::residuals`]; the polynomial as [`super::polynomial`] evaluates it.
///
/// # Safety
///
/// As [`moments`].
#[inline(always)]
unsafe fn residuals<Q: Quad, const N: usize>(cols: &mut Columns, c: &[f64; N]) -> f64 {
    let cs: [Q; N] = std::array::from_fn(|k| Q::splat(c[k]));
    let one = Q::splat(1.0);
    let mut ss = Q::splat(0.0);
    for g in &mut cols.groups {
        let (a, b, z) = (Q::load(&g.a), Q::load(&g.b), Q::load(&g.z));
        let linear = cs[0].add(cs[1].mul(a)).add(cs[2].mul(b));
        let fit = if N < 6 {
            linear
        } else {
            linear
                .add(a.mul(cs[3].mul(a).add(cs[4].mul(b))))
                .add(cs[5].mul(b).mul(b))
        };
        let resid = z.sub(one.div(fit)).abs();
        resid.store(&mut g.resid);
        ss = ss.add(resid.mul(resid).and(Q::load_mask(&g.keep)));
    }
    ss.sum()
}

/// See [`Columns::drop_beyond`].
///
/// # Safety
///
/// As [`moments`].
#[inline(always)]
unsafe fn drop_beyond<Q: Quad>(cols: &mut Columns, cut: f64, moments: &mut Moments) -> usize {
    let cut = Q::splat(cut);
    let mut dropped = 0;
    for g in &mut cols.groups {
        let mut bits = Q::load(&g.resid).above_where(cut, Q::load_mask(&g.keep));
        while bits != 0 {
            let k = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            g.keep[k] = 0;
            moments.take_out(g.a[k], g.b[k], g.w[k], g.rhs[k]);
            dropped += 1;
        }
    }
    dropped
}

#[cfg(target_arch = "x86_64")]
mod avx {
    //! The sums built for AVX2, one group per register.

    use std::arch::x86_64::*;

    use super::{Columns, Moments, Quad};

    impl Quad for __m256d {
        #[inline(always)]
        fn splat(v: f64) -> Self {
            // SAFETY (each intrinsic here): only reached from the `target_feature(enable = "avx2")`
            // functions below, which run after the processor was found to have AVX2.
            unsafe { _mm256_set1_pd(v) }
        }
        #[inline(always)]
        fn load(s: &[f64; 4]) -> Self {
            // SAFETY: four `f64`; unaligned load.
            unsafe { _mm256_loadu_pd(s.as_ptr()) }
        }
        #[inline(always)]
        fn load_mask(s: &[u64; 4]) -> Self {
            // SAFETY: four `u64`; unaligned load.
            unsafe { _mm256_castsi256_pd(_mm256_loadu_si256(s.as_ptr().cast())) }
        }
        #[inline(always)]
        fn store(self, s: &mut [f64; 4]) {
            // SAFETY: four `f64`; unaligned store.
            unsafe { _mm256_storeu_pd(s.as_mut_ptr(), self) }
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            unsafe { _mm256_add_pd(self, o) }
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            unsafe { _mm256_sub_pd(self, o) }
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            unsafe { _mm256_mul_pd(self, o) }
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            unsafe { _mm256_div_pd(self, o) }
        }
        #[inline(always)]
        fn abs(self) -> Self {
            unsafe { _mm256_andnot_pd(_mm256_set1_pd(-0.0), self) }
        }
        #[inline(always)]
        fn and(self, mask: Self) -> Self {
            unsafe { _mm256_and_pd(self, mask) }
        }
        #[inline(always)]
        fn above_where(self, v: Self, mask: Self) -> u32 {
            unsafe { _mm256_movemask_pd(_mm256_and_pd(_mm256_cmp_pd::<_CMP_GT_OQ>(self, v), mask)) as u32 }
        }
        #[inline(always)]
        fn sum(self) -> f64 {
            let mut l = [0.0; 4];
            // SAFETY: four `f64` into `l`.
            unsafe { _mm256_storeu_pd(l.as_mut_ptr(), self) };
            (l[0] + l[1]) + (l[2] + l[3])
        }
    }

    // SAFETY (each call below): these functions are built for AVX2, so the processor has it
    // whenever they run (their callers check).

    #[target_feature(enable = "avx2")]
    pub(super) fn moments(cols: &Columns, quartic: bool) -> Moments {
        unsafe { super::moments::<__m256d>(cols, quartic) }
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn residuals<const N: usize>(cols: &mut Columns, c: &[f64; N]) -> f64 {
        unsafe { super::residuals::<__m256d, N>(cols, c) }
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn drop_beyond(cols: &mut Columns, cut: f64, moments: &mut Moments) -> usize {
        unsafe { super::drop_beyond::<__m256d>(cols, cut, moments) }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{fit_inverse_depth, InverseDepthFit, Robust};
    use super::*;

    /// A window of `n` points on a curved layer near 600 mm, with depth noise and
    /// some points far off it (another surface), from `seed`.
    fn window(n: usize, seed: u64) -> Vec<RayPoint> {
        let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut uniform = move || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let (ca, cb) = (uniform() * 0.4 - 0.2, uniform() * 0.4 - 0.2);
        let (ga, gb, curve) = (uniform() - 0.5, uniform() - 0.5, uniform() * 4.0);
        let noise_mm = 0.5 + uniform() * 6.0;
        (0..n)
            .map(|_| {
                let (a, b) = (ca + (uniform() - 0.5) * 0.04, cb + (uniform() - 0.5) * 0.04);
                let inv = 1.0 / 600.0 * (1.0 + ga * (a - ca) + gb * (b - cb) + curve * (a - ca) * (a - ca));
                let mut z = 1.0 / inv + noise_mm * (uniform() + uniform() + uniform() - 1.5) * 2.0;
                if uniform() < 0.06 {
                    z += 30.0 + uniform() * 200.0;
                }
                RayPoint {
                    a,
                    b,
                    z,
                    distance: z * (1.0 + a * a + b * b).sqrt(),
                }
            })
            .collect()
    }

    fn same<const N: usize>(x: &Option<InverseDepthFit<N>>, y: &Option<InverseDepthFit<N>>) -> bool {
        match (x, y) {
            (None, None) => true,
            (Some(x), Some(y)) => {
                x.coef.map(f64::to_bits) == y.coef.map(f64::to_bits)
                    && x.rms.to_bits() == y.rms.to_bits()
                    && x.sigma.to_bits() == y.sigma.to_bits()
                    && x.count == y.count
            }
            _ => false,
        }
    }

    /// The fit written plainly: sums in point order, the kept points summed again
    /// each pass.
    fn plain<const N: usize>(points: &[RayPoint], (a0, b0): (f64, f64), robust: &Robust) -> Option<([f64; N], usize)> {
        let mono = |a: f64, b: f64| [1.0, a, b, a * a, a * b, b * b];
        let mut keep = vec![true; points.len()];
        let mut out = None;
        for pass in 0..=robust.passes {
            let mut ata = [[0.0; N]; N];
            let mut atb = [0.0; N];
            for (p, _) in points.iter().zip(&keep).filter(|(_, &k)| k) {
                let m = mono(p.a - a0, p.b - b0);
                let w = p.z.powi(4);
                for i in 0..N {
                    for j in 0..N {
                        ata[i][j] += w * m[i] * m[j];
                    }
                    atb[i] += w / p.z * m[i];
                }
            }
            let c = nalgebra::SMatrix::<f64, N, N>::from_fn(|i, j| ata[i][j])
                .cholesky()?
                .solve(&nalgebra::SVector::<f64, N>::from_fn(|i, _| atb[i]));
            let c: [f64; N] = std::array::from_fn(|i| c[i]);
            let resid: Vec<f64> = points
                .iter()
                .map(|p| {
                    let m = mono(p.a - a0, p.b - b0);
                    (p.z - 1.0 / (0..N).map(|i| c[i] * m[i]).sum::<f64>()).abs()
                })
                .collect();
            let n = keep.iter().filter(|&&k| k).count();
            let ss: f64 = resid.iter().zip(&keep).filter(|(_, &k)| k).map(|(r, _)| r * r).sum();
            out = Some((c, n));
            let cut = (robust.k * (ss / n as f64).sqrt()).max(robust.floor_mm);
            let before = n;
            for (k, r) in keep.iter_mut().zip(&resid) {
                *k &= *r <= cut;
            }
            if pass == robust.passes || keep.iter().filter(|&&k| k).count() == before {
                break;
            }
        }
        out
    }

    #[test]
    fn the_same_with_and_without_avx2() {
        // Windows of every length mod 4, quadrics and planes: the fits of the code built for
        // this processor and of the code built for any processor, bit for bit.
        if !crate::physics::vector::avx2() {
            eprintln!("no AVX2 here: the portable code is compared with itself");
        }
        let robust = Robust {
            k: 2.5,
            floor_mm: 1.0,
            passes: 2,
        };
        let mut dropped = 0;
        for seed in 0..400u64 {
            let points = window(12 + (seed as usize % 90), seed);
            let centre = (points[0].a, points[0].b);
            let q = fit_inverse_depth::<6>(&points, centre, 10, &robust);
            let p = fit_inverse_depth::<3>(&points, centre, 3, &robust);
            assert!(
                same(&q, &portable(|| fit_inverse_depth::<6>(&points, centre, 10, &robust))),
                "seed {seed}"
            );
            assert!(
                same(&p, &portable(|| fit_inverse_depth::<3>(&points, centre, 3, &robust))),
                "seed {seed}"
            );
            dropped += points.len() - q.map_or(points.len(), |q| q.count);
        }
        assert!(
            dropped > 400,
            "the passes dropped {dropped} points: too few to test the drops"
        );
    }

    /// The fits of `N` terms of 300 seeded windows against the plain ones: how many compared.
    fn compare_with_plain<const N: usize>(min_points: usize) -> usize {
        let robust = Robust {
            k: 2.5,
            floor_mm: 1.0,
            passes: 2,
        };
        let mut compared = 0;
        for seed in 0..300u64 {
            let points = window(20 + (seed as usize % 70), 1000 + seed);
            let centre = (points[0].a, points[0].b);
            let fit = fit_inverse_depth::<N>(&points, centre, min_points, &robust);
            let plain = plain::<N>(&points, centre, &robust);
            let (Some(fit), Some((c, count))) = (fit, plain) else {
                // Only where neither fits (a degenerate window), not one alone.
                assert!(fit.is_none() && plain.is_none(), "N {N}, seed {seed}: one fit only");
                continue;
            };
            assert_eq!(fit.count, count, "N {N}, seed {seed}");
            // Compared as inverse depths at the window's points, relative to 1/600 mm.
            for p in &points {
                let (a, b) = (p.a - centre.0, p.b - centre.1);
                let d = (super::super::polynomial(&fit.coef, a, b) - super::super::polynomial(&c, a, b)).abs() * 600.0;
                assert!(d < 1e-9, "N {N}, seed {seed}: {d}");
            }
            compared += 1;
        }
        compared
    }

    #[test]
    fn fits_what_the_plain_sums_fit() {
        // The moments, residuals and drops against the fit written plainly: the same points
        // kept and the same coefficients to rounding, quadrics and planes.
        let quadrics = compare_with_plain::<6>(10);
        let planes = compare_with_plain::<3>(3);
        assert!(quadrics > 250 && planes > 250, "{quadrics} quadrics, {planes} planes");
    }

    #[test]
    fn padding_is_never_kept() {
        let mut cols = Columns::default();
        for n in 0..9 {
            let points = window(n, 7);
            cols.fill(&points, (0.0, 0.0));
            assert_eq!(cols.groups.len(), n.div_ceil(4));
            let kept: usize = cols
                .groups
                .iter()
                .map(|g| g.keep.iter().filter(|&&k| k == KEPT).count())
                .sum();
            assert_eq!(kept, n);
            let m = cols.moments(true);
            let w: f64 = points.iter().map(|p| p.z.powi(4)).sum();
            assert!((m.w[0] - w).abs() <= 1e-12 * w, "{n}");
        }
    }
}
