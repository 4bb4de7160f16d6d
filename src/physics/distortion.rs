//! Lens distortion of the ROS camera models (`sensor_msgs/CameraInfo`'s
//! `distortion_model` and `d`), on normalized image coordinates: a pinhole
//! point `(x/z, y/z)` is distorted to where the lens puts it, `(u - cx)/fx,
//! (v - cy)/fy` at full resolution.

/// Largest number of Newton steps [`Distortion::undistort`] takes.
const MAX_STEPS: usize = 60;
/// A solution is accepted when it distorts to within this of the point
/// (normalized units); the undistorted error is then far below 1e-9.
const TOLERANCE: f64 = 1e-14;

/// A lens distortion model with its coefficients, in ROS's order.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Distortion {
    /// A pinhole: no distortion.
    #[default]
    None,
    /// `plumb_bob`: k1 k2 p1 p2 k3 (radial and tangential, OpenCV's 5 coefficients).
    PlumbBob([f64; 5]),
    /// `rational_polynomial`: k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV's 8 coefficients).
    Rational([f64; 8]),
    /// `equidistant`: k1 k2 k3 k4 (OpenCV's fisheye, `theta_d = theta (1 + k1 theta^2 + ...)`).
    Equidistant([f64; 4]),
}

/// Why a distortion model is not usable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DistortionError {
    /// A model name other than ROS's three.
    #[error("distortion model {0:?} is not supported (expected plumb_bob, rational_polynomial or equidistant)")]
    UnknownModel(String),
    /// The model needs another number of coefficients.
    #[error("distortion model {model} needs {expected} coefficients in D, got {got}")]
    CoefficientCount {
        /// The model.
        model: &'static str,
        /// Coefficients it takes.
        expected: usize,
        /// Coefficients given.
        got: usize,
    },
    /// A coefficient is NaN or infinite.
    #[error("distortion coefficient D[{index}] is {value} (must be finite)")]
    NonFinite {
        /// Its index in `d`.
        index: usize,
        /// Its value.
        value: f64,
    },
}

impl Distortion {
    /// From camera_info's `distortion_model` and `d`. An empty or all-zero
    /// `d` is no distortion under a known model or an empty name (as ROS's
    /// image_geometry takes it, `equidistant` too).
    pub fn from_ros(model: &str, d: &[f64]) -> Result<Self, DistortionError> {
        if let Some((index, &value)) = d.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(DistortionError::NonFinite { index, value });
        }
        let known = ["plumb_bob", "rational_polynomial", "equidistant"].contains(&model);
        let zero = d.iter().all(|&v| v == 0.0);
        if !(known || model.is_empty() && zero) {
            return Err(DistortionError::UnknownModel(model.into()));
        }
        if zero {
            return Ok(Self::None);
        }
        match model {
            "plumb_bob" => Ok(Self::PlumbBob(coefficients("plumb_bob", d)?)),
            "rational_polynomial" => Ok(Self::Rational(coefficients("rational_polynomial", d)?)),
            _ => Ok(Self::Equidistant(coefficients("equidistant", d)?)),
        }
    }

    /// camera_info's `distortion_model` and `d` (no distortion: `plumb_bob`, five zeros).
    pub fn to_ros(&self) -> (&'static str, Vec<f64>) {
        match self {
            Self::None => ("plumb_bob", vec![0.0; 5]),
            Self::PlumbBob(c) => ("plumb_bob", c.to_vec()),
            Self::Rational(c) => ("rational_polynomial", c.to_vec()),
            Self::Equidistant(c) => ("equidistant", c.to_vec()),
        }
    }

    /// Where the lens puts the pinhole point `p`; `None` where the model
    /// has no image of it (beyond 90 degrees for the fisheye).
    pub fn distort(&self, p: [f64; 2]) -> Option<[f64; 2]> {
        match self {
            Self::None => Some(p),
            Self::PlumbBob([k1, k2, p1, p2, k3]) => {
                Some(radial_tangential(p, [*k1, *k2, *k3, 0.0, 0.0, 0.0], [*p1, *p2]).0)
            }
            Self::Rational([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                Some(radial_tangential(p, [*k1, *k2, *k3, *k4, *k5, *k6], [*p1, *p2]).0)
            }
            Self::Equidistant(k) => {
                let r = p[0].hypot(p[1]);
                let scale = if r > 0.0 {
                    fisheye_theta_d(k, r.atan()).0 / r
                } else {
                    1.0
                };
                scale.is_finite().then_some([p[0] * scale, p[1] * scale])
            }
        }
    }

    /// The pinhole point the lens put at `q`: the inverse of
    /// [`Self::distort`] on the region where the model is one-to-one;
    /// `None` where it has no converged solution there (outside the
    /// model's valid region).
    pub fn undistort(&self, q: [f64; 2]) -> Option<[f64; 2]> {
        if !(q[0].is_finite() && q[1].is_finite()) {
            return None;
        }
        match self {
            Self::None => Some(q),
            Self::PlumbBob([k1, k2, p1, p2, k3]) => {
                invert_radial_tangential(q, [*k1, *k2, *k3, 0.0, 0.0, 0.0], [*p1, *p2])
            }
            Self::Rational([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                invert_radial_tangential(q, [*k1, *k2, *k3, *k4, *k5, *k6], [*p1, *p2])
            }
            Self::Equidistant(k) => invert_fisheye(k, q),
        }
    }
}

fn coefficients<const N: usize>(model: &'static str, d: &[f64]) -> Result<[f64; N], DistortionError> {
    d.try_into().map_err(|_| DistortionError::CoefficientCount {
        model,
        expected: N,
        got: d.len(),
    })
}

/// The radial-tangential model at `p` with radial `k = [k1..k6]` (k4..k6 in
/// the denominator) and tangential `t = [p1, p2]`; with its Jacobian
/// `[[dx/dx, dx/dy], [dy/dx, dy/dy]]`.
fn radial_tangential(p: [f64; 2], k: [f64; 6], t: [f64; 2]) -> ([f64; 2], [[f64; 2]; 2]) {
    let [x, y] = p;
    let r2 = x * x + y * y;
    let (s, ds) = radial_scale(&k, r2);
    let [p1, p2] = t;
    let xd = x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let cross = 2.0 * x * y * ds + 2.0 * p1 * x + 2.0 * p2 * y;
    let jac = [
        [s + 2.0 * x * x * ds + 2.0 * p1 * y + 6.0 * p2 * x, cross],
        [cross, s + 2.0 * y * y * ds + 6.0 * p1 * y + 2.0 * p2 * x],
    ];
    ([xd, yd], jac)
}

/// The radial factor `s(r2)` with radial `k = [k1..k6]` and `ds/d(r2)`.
fn radial_scale(k: &[f64; 6], r2: f64) -> (f64, f64) {
    let num = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]));
    let den = 1.0 + r2 * (k[3] + r2 * (k[4] + r2 * k[5]));
    let dnum = k[0] + r2 * (2.0 * k[1] + 3.0 * r2 * k[2]);
    let dden = k[3] + r2 * (2.0 * k[4] + 3.0 * r2 * k[5]);
    (num / den, (dnum * den - num * dden) / (den * den))
}

/// Newton's method on [`radial_tangential`], started at `q`, each step
/// halved until the residual falls; the solution must lie where the radial
/// distortion still rises from the centre (not on a branch past a fold).
fn invert_radial_tangential(q: [f64; 2], k: [f64; 6], t: [f64; 2]) -> Option<[f64; 2]> {
    let residual = |p: [f64; 2]| {
        let (d, jac) = radial_tangential(p, k, t);
        ([d[0] - q[0], d[1] - q[1]], jac)
    };
    let mut p = q;
    let (mut e, mut jac) = residual(p);
    for _ in 0..MAX_STEPS {
        let norm = e[0].hypot(e[1]);
        let det = jac[0][0] * jac[1][1] - jac[0][1] * jac[1][0];
        if norm <= TOLERANCE {
            // The radial image r s(r^2) rises (its derivative s + 2 r^2 s' is positive).
            let rises = |r: f64| {
                let (s, ds) = radial_scale(&k, r * r);
                s > 0.0 && s + 2.0 * r * r * ds > 0.0
            };
            return rising_up_to(p[0].hypot(p[1]), rises).then_some(p);
        }
        if !(det.is_finite() && det != 0.0) {
            return None;
        }
        let step = [
            (jac[1][1] * e[0] - jac[0][1] * e[1]) / det,
            (jac[0][0] * e[1] - jac[1][0] * e[0]) / det,
        ];
        let mut scale = 1.0;
        loop {
            let next = [p[0] - scale * step[0], p[1] - scale * step[1]];
            let (ne, nj) = residual(next);
            if ne[0].hypot(ne[1]) < norm || scale < 1e-6 {
                (p, e, jac) = (next, ne, nj);
                break;
            }
            scale *= 0.5;
        }
        if !(p[0].is_finite() && p[1].is_finite()) {
            return None;
        }
    }
    None
}

/// Whether `rises` holds at 64 radii evenly spaced up to `r`: the model is
/// one-to-one from the centre out to the solution.
fn rising_up_to(r: f64, rises: impl Fn(f64) -> bool) -> bool {
    (1..=64).all(|i| rises(r * f64::from(i) / 64.0))
}

/// `theta_d` of the fisheye at `theta` and its derivative.
fn fisheye_theta_d(k: &[f64; 4], theta: f64) -> (f64, f64) {
    let t2 = theta * theta;
    let poly = 1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])));
    let dpoly = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
    (theta * poly, dpoly)
}

/// The fisheye's radial inverse by Newton on `theta`: the solution must lie
/// in front of the camera (below 90 degrees), with `theta_d` still rising.
fn invert_fisheye(k: &[f64; 4], q: [f64; 2]) -> Option<[f64; 2]> {
    let theta_d = q[0].hypot(q[1]);
    if theta_d == 0.0 {
        return Some(q);
    }
    let limit = std::f64::consts::FRAC_PI_2;
    let mut theta = theta_d.min(limit * 0.999);
    for _ in 0..MAX_STEPS {
        let (f, df) = fisheye_theta_d(k, theta);
        let e = f - theta_d;
        if e.abs() <= TOLERANCE {
            if !(theta > 0.0 && theta < limit && rising_up_to(theta, |t| fisheye_theta_d(k, t).1 > 0.0)) {
                return None;
            }
            let scale = theta.tan() / theta_d;
            return Some([q[0] * scale, q[1] * scale]);
        }
        if !(df.is_finite() && df > 0.0) {
            return None;
        }
        // Kept within (0, 90 degrees): halfway to the bound when a step would leave it.
        let next = theta - e / df;
        theta = if next <= 0.0 {
            theta / 2.0
        } else if next >= limit {
            (theta + limit) / 2.0
        } else {
            next
        };
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn models() -> Vec<Distortion> {
        vec![
            Distortion::PlumbBob([-0.3, 0.1, 0.001, -0.002, 0.0]),
            Distortion::PlumbBob([0.12, -0.25, -0.0015, 0.0008, 0.09]),
            Distortion::Rational([0.4, -0.1, 0.001, 0.002, 0.01, 0.6, -0.05, 0.02]),
            Distortion::Equidistant([0.05, -0.01, 0.003, -0.0005]),
            Distortion::Equidistant([-0.02, 0.004, 0.0, 0.0]),
        ]
    }

    #[test]
    fn undistort_inverts_distort_over_a_wide_field() {
        for m in models() {
            for i in 0..=40 {
                for j in 0..=40 {
                    // Pinhole points up to 0.9 in x/z and y/z (about 42 degrees off the axis each way).
                    let p = [-0.9 + 0.045 * i as f64, -0.9 + 0.045 * j as f64];
                    let q = m.distort(p).unwrap();
                    let back = m.undistort(q).unwrap_or_else(|| panic!("{m:?} at {p:?}"));
                    let err = (back[0] - p[0]).hypot(back[1] - p[1]);
                    assert!(err < 1e-9, "{m:?} at {p:?}: {err:e}");
                }
            }
        }
    }

    #[test]
    fn plumb_bob_matches_a_hand_computation() {
        // x = 0.2, y = -0.1: r2 = 0.05; radial 1 - 0.3*0.05 + 0.1*0.0025 + 0.05*0.000125 = 0.98525625;
        // x: 0.2*0.98525625 + 2*0.01*0.2*(-0.1) + 0.02*(0.05 + 0.08) = 0.19925125
        // y: -0.1*0.98525625 + 0.01*(0.05 + 0.02) + 2*0.02*0.2*(-0.1) = -0.098625625
        let m = Distortion::PlumbBob([-0.3, 0.1, 0.01, 0.02, 0.05]);
        let q = m.distort([0.2, -0.1]).unwrap();
        assert!((q[0] - 0.19925125).abs() < 1e-14, "{q:?}");
        assert!((q[1] + 0.098625625).abs() < 1e-14, "{q:?}");
        let p = m.undistort(q).unwrap();
        assert!((p[0] - 0.2).abs() < 1e-12 && (p[1] + 0.1).abs() < 1e-12, "{p:?}");
    }

    #[test]
    fn equidistant_matches_a_hand_computation() {
        // r = 1 (45 degrees): theta = pi/4, theta_d = theta (1 + 0.1 theta^2).
        let m = Distortion::Equidistant([0.1, 0.0, 0.0, 0.0]);
        let t = std::f64::consts::FRAC_PI_4;
        let q = m.distort([1.0, 0.0]).unwrap();
        assert!((q[0] - t * (1.0 + 0.1 * t * t)).abs() < 1e-15 && q[1] == 0.0, "{q:?}");
    }

    #[test]
    fn zero_coefficients_are_a_pinhole() {
        for (name, n) in [
            ("plumb_bob", 5),
            ("rational_polynomial", 8),
            ("equidistant", 4),
            ("plumb_bob", 0),
            ("", 0),
        ] {
            assert_eq!(
                Distortion::from_ros(name, &vec![0.0; n]),
                Ok(Distortion::None),
                "{name} {n}"
            );
        }
        for m in [
            Distortion::PlumbBob([0.0; 5]),
            Distortion::Rational([0.0; 8]),
            Distortion::Equidistant([0.0; 4]),
        ] {
            let p = [0.3, -0.2];
            let q = m.distort(p).unwrap();
            // The fisheye with zero k is equidistant, not a pinhole: theta_d = theta.
            if matches!(m, Distortion::Equidistant(_)) {
                let r = p[0].hypot(p[1]);
                assert!((q[0].hypot(q[1]) - r.atan()).abs() < 1e-15);
            } else {
                assert_eq!(q, p);
            }
        }
    }

    #[test]
    fn bad_models_are_named() {
        let e = Distortion::from_ros("kannala_brandt", &[0.1; 4]).unwrap_err();
        assert!(e.to_string().contains("kannala_brandt"), "{e}");
        let e = Distortion::from_ros("plumb_bob", &[0.1; 4]).unwrap_err();
        assert_eq!(
            e,
            DistortionError::CoefficientCount {
                model: "plumb_bob",
                expected: 5,
                got: 4
            }
        );
        let e = Distortion::from_ros("equidistant", &[0.1, f64::NAN, 0.0, 0.0]).unwrap_err();
        assert!(matches!(e, DistortionError::NonFinite { index: 1, .. }), "{e}");
        assert!(Distortion::from_ros("", &[0.1; 5]).is_err());
        let (name, d) = Distortion::Rational([0.5; 8]).to_ros();
        assert_eq!(Distortion::from_ros(name, &d), Ok(Distortion::Rational([0.5; 8])));
    }

    #[test]
    fn beyond_the_valid_region_there_is_no_ray() {
        // Barrel distortion r_d = r (1 - 0.5 r^2) peaks at r_d = 0.544 (r = 0.816): nothing lies beyond.
        let m = Distortion::PlumbBob([-0.5, 0.0, 0.0, 0.0, 0.0]);
        assert!(m.undistort([0.5, 0.0]).is_some());
        assert!(m.undistort([0.6, 0.0]).is_none());
        // The fisheye at theta_d past 90 degrees has no point in front of the camera.
        let f = Distortion::Equidistant([0.0; 4]);
        assert!(f.undistort([1.4, 0.0]).is_some());
        assert!(f.undistort([1.7, 0.0]).is_none());
        assert!(m.undistort([f64::NAN, 0.0]).is_none());
    }
}
