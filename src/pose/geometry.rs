//! Camera intrinsics, rigid poses (camera-from-object) and their local
//! update by a 6-d twist.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::PoseError;

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Checks that every value is finite and the focal lengths positive;
    /// the error names the first field that is not.
    pub fn validate(&self) -> Result<(), PoseError> {
        let fields = [
            ("fx", self.fx, true),
            ("fy", self.fy, true),
            ("cx", self.cx, false),
            ("cy", self.cy, false),
        ];
        for (name, v, positive) in fields {
            if !v.is_finite() || (positive && v <= 0.0) {
                let need = if positive {
                    "a finite number above 0 (pixels)"
                } else {
                    "a finite number (pixels)"
                };
                return Err(PoseError::InvalidParameter(format!(
                    "intrinsics.{name} must be {need}, got {v}"
                )));
            }
        }
        Ok(())
    }

    /// The pixel of a camera-frame point in front of the camera.
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        (p.z > 1e-9)
            .then(|| Vector2::new(self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// The derivative of [`Self::project`] at `p` (2x3, rows u and v).
    #[inline]
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> [[f64; 3]; 2] {
        let iz = 1.0 / p.z;
        [
            [self.fx * iz, 0.0, -self.fx * p.x * iz * iz],
            [0.0, self.fy * iz, -self.fy * p.y * iz * iz],
        ]
    }
}

/// A rigid transform from object to camera coordinates: `x_cam = R x + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

/// Largest Frobenius distance between a client's rotation and the nearest
/// rotation that is accepted (and projected) rather than refused.
pub const ROTATION_TOLERANCE: f64 = 0.05;

impl Pose {
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// A pose from a rotation given by a client: a nearly orthonormal
    /// matrix is projected to the nearest rotation (SVD); one further than
    /// [`ROTATION_TOLERANCE`] from it, a reflection or non-finite values are
    /// refused.
    pub fn from_client(rotation: [[f64; 3]; 3], translation: [f64; 3]) -> Result<Self, PoseError> {
        let m = Matrix3::from_fn(|r, c| rotation[r][c]);
        let t = Vector3::from(translation);
        if m.iter().chain(t.iter()).any(|v| !v.is_finite()) {
            return Err(PoseError::InvalidParameter(
                "the pose has non-finite values".into(),
            ));
        }
        let r = nearest_rotation(&m)
            .ok_or_else(|| PoseError::InvalidParameter("the rotation is degenerate".into()))?;
        let d = (m - r).norm();
        if d > ROTATION_TOLERANCE || m.determinant() <= 0.0 {
            return Err(PoseError::InvalidParameter(format!(
                "the rotation is not a rotation: {d:.3} from the nearest one (at most {ROTATION_TOLERANCE} is projected), determinant {:.3}",
                m.determinant()
            )));
        }
        Ok(Self {
            rotation: r,
            translation: t,
        })
    }

    #[inline]
    pub fn transform(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// The pose after a twist `xi = (v, w)` applied on the camera side:
    /// every camera-frame point `P` moves to `exp([w]) P + v`. To first
    /// order `P + v + w x P`, which is what the Jacobians use.
    pub fn updated(&self, xi: &Vector6<f64>) -> Self {
        let v = Vector3::new(xi[0], xi[1], xi[2]);
        let w = Vector3::new(xi[3], xi[4], xi[5]);
        let dr = Rotation3::new(w).into_inner();
        Self {
            rotation: dr * self.rotation,
            translation: dr * self.translation + v,
        }
    }

    /// `[w, x, y, z]` of the rotation.
    pub fn quaternion(&self) -> [f64; 4] {
        let q = UnitQuaternion::from_matrix(&self.rotation);
        // q and -q are the same rotation: answer the one with w >= 0.
        let s = if q.w < 0.0 { -1.0 } else { 1.0 };
        [s * q.w, s * q.i, s * q.j, s * q.k]
    }

    /// Rows of the rotation matrix.
    pub fn rotation_rows(&self) -> [[f64; 3]; 3] {
        let r = &self.rotation;
        [
            [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
            [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
            [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
        ]
    }

    /// Rotation angle (radians) and translation distance from `other`.
    pub fn distance(&self, other: &Pose) -> (f64, f64) {
        let dr = self.rotation * other.rotation.transpose();
        let c = ((dr.trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
        (c.acos(), (self.translation - other.translation).norm())
    }

    /// Roll, pitch and yaw (x, y, z Euler angles, radians) of the rotation.
    pub fn euler(&self) -> (f64, f64, f64) {
        Rotation3::from_matrix_unchecked(self.rotation).euler_angles()
    }
}

/// The box `(x, y, w, h)` of `points` (object coordinates) projected at
/// `pose`, those in front of the camera; `None` when none is.
pub fn projected_box(
    points: &[Vector3<f64>],
    k: &Intrinsics,
    pose: &Pose,
) -> Option<(f64, f64, f64, f64)> {
    let mut lo = Vector2::new(f64::INFINITY, f64::INFINITY);
    let mut hi = Vector2::new(f64::NEG_INFINITY, f64::NEG_INFINITY);
    for p in points.iter().filter_map(|v| k.project(&pose.transform(v))) {
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    (lo.x <= hi.x && lo.y <= hi.y).then(|| (lo.x, lo.y, hi.x - lo.x, hi.y - lo.y))
}

/// The rotation nearest to `m` in the Frobenius norm (`U diag(1, 1, d) V^T`).
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let d = (u * vt).determinant().signum();
    let s = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d));
    Some(u * s * vt)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearly_orthonormal_rotations_are_projected_and_others_refused() {
        let r = Rotation3::from_euler_angles(0.3, -0.2, 1.1).into_inner();
        let mut noisy = r;
        noisy[(0, 1)] += 0.01;
        noisy[(2, 2)] -= 0.008;
        let rows = |m: &Matrix3<f64>| {
            [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ]
        };
        let p = Pose::from_client(rows(&noisy), [0.0, 0.0, 1.0]).unwrap();
        assert!((p.rotation * p.rotation.transpose() - Matrix3::identity()).norm() < 1e-12);
        assert!((p.rotation.determinant() - 1.0).abs() < 1e-12);
        assert!((p.rotation - r).norm() < 0.02);
        let mut far = r;
        far[(0, 0)] += 0.5;
        assert!(Pose::from_client(rows(&far), [0.0; 3]).is_err());
        let reflection = -r;
        assert!(Pose::from_client(rows(&reflection), [0.0; 3]).is_err());
        let mut nan = r;
        nan[(1, 1)] = f64::NAN;
        assert!(Pose::from_client(rows(&nan), [0.0; 3]).is_err());
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let k = Intrinsics {
            fx: 600.0,
            fy: 610.0,
            cx: 320.0,
            cy: 240.0,
        };
        let p = Vector3::new(0.05, -0.03, 0.5);
        let j = k.project_jacobian(&p);
        let h = 1e-7;
        for a in 0..3 {
            let mut q = p;
            q[a] += h;
            let d = (k.project(&q).unwrap() - k.project(&p).unwrap()) / h;
            assert!((d.x - j[0][a]).abs() < 1e-3 * (1.0 + j[0][a].abs()));
            assert!((d.y - j[1][a]).abs() < 1e-3 * (1.0 + j[1][a].abs()));
        }
    }

    #[test]
    fn twist_update_is_first_order_translation_plus_rotation() {
        let pose = Pose {
            rotation: Rotation3::from_euler_angles(0.1, 0.2, 0.3).into_inner(),
            translation: Vector3::new(0.01, 0.02, 0.5),
        };
        let x = Vector3::new(0.03, -0.02, 0.04);
        let p = pose.transform(&x);
        let xi = Vector6::new(1e-6, -2e-6, 3e-6, 2e-6, 1e-6, -3e-6);
        let moved = pose.updated(&xi).transform(&x);
        let v = Vector3::new(xi[0], xi[1], xi[2]);
        let w = Vector3::new(xi[3], xi[4], xi[5]);
        let predicted = p + v + w.cross(&p);
        assert!((moved - predicted).norm() < 1e-10);
    }
}
