//! Orthonormal frames: local shading space has the normal on +z.

use glam::Vec3;

/// An orthonormal basis (s, t, n); `to_local` / `to_world` move directions
/// between world space and the shading space where the normal is +z.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Builds a frame around a unit normal with the branchless construction of
    /// Duff et al. 2017, which is continuous except at n.z = -0 and never
    /// produces NaN for a unit input.
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Self { s, t, n }
    }

    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn frame_is_orthonormal(x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0) {
            let v = Vec3::new(x, y, z);
            prop_assume!(v.length() > 1e-3);
            let f = Frame::from_normal(v.normalize());
            prop_assert!((f.s.length() - 1.0).abs() < 1e-4);
            prop_assert!((f.t.length() - 1.0).abs() < 1e-4);
            prop_assert!(f.s.dot(f.t).abs() < 1e-4);
            prop_assert!(f.s.dot(f.n).abs() < 1e-4);
            prop_assert!(f.t.dot(f.n).abs() < 1e-4);
            let w = Vec3::new(0.3, -0.5, 0.8);
            prop_assert!((f.to_world(f.to_local(w)) - w).length() < 1e-4);
        }
    }
}
