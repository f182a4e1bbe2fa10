//! The point of a triangle closest to a given point (Ericson, "Real-Time
//! Collision Detection", 5.1.5): which Voronoi region of the triangle the
//! point projects into, decided from dot products alone, then the point of
//! that vertex, edge or face. The renderer moves an estimator's predicted
//! vertex onto the real surface with it.

use glam::Vec3;

/// The point of triangle `a`, `b`, `c` closest to `p`, with its
/// barycentric coordinates `(b1, b2)` (the point is
/// `a (1 - b1 - b2) + b b1 + c b2`, as a ray hit's). A degenerate triangle
/// (collinear or coincident corners) gets the closest point of its longest
/// edge or its corner.
pub fn closest_point_on_triangle(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> (Vec3, f32, f32) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, 0.0, 0.0);
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, 1.0, 0.0);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = edge_fraction(d1, d1 - d3);
        return (a + ab * v, v, 0.0);
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, 0.0, 1.0);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = edge_fraction(d2, d2 - d6);
        return (a + ac * w, 0.0, w);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = edge_fraction(d4 - d3, (d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, 1.0 - w, w);
    }
    let sum = va + vb + vc;
    if !(sum > 0.0 && sum.is_finite()) {
        // Degenerate: the face region is empty; the edges' answers hold.
        return degenerate(p, a, b, c);
    }
    let v = vb / sum;
    let w = vc / sum;
    (a + ab * v + ac * w, v, w)
}

/// `num / den` in [0, 1] (0 for an empty edge).
#[inline]
fn edge_fraction(num: f32, den: f32) -> f32 {
    if den > 0.0 {
        (num / den).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// The closest of the three edges' closest points.
fn degenerate(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> (Vec3, f32, f32) {
    let on_edge = |s: Vec3, e: Vec3| {
        let d = e - s;
        let t = edge_fraction((p - s).dot(d), d.length_squared());
        (s + d * t, t)
    };
    let (q_ab, t_ab) = on_edge(a, b);
    let (q_ac, t_ac) = on_edge(a, c);
    let (q_bc, t_bc) = on_edge(b, c);
    [
        (q_ab, t_ab, 0.0),
        (q_ac, 0.0, t_ac),
        (q_bc, 1.0 - t_bc, t_bc),
    ]
    .into_iter()
    .min_by(|x, y| p.distance_squared(x.0).total_cmp(&p.distance_squared(y.0)))
    .unwrap_or((a, 0.0, 0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn v3() -> impl Strategy<Value = Vec3> {
        (-10.0f32..10.0, -10.0f32..10.0, -10.0f32..10.0).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    #[test]
    fn regions_of_a_right_triangle() {
        let (a, b, c) = (Vec3::ZERO, Vec3::X, Vec3::Y);
        // Above the face: straight down.
        let (q, b1, b2) = closest_point_on_triangle(Vec3::new(0.25, 0.25, 3.0), a, b, c);
        assert!(q.distance(Vec3::new(0.25, 0.25, 0.0)) < 1e-6);
        assert!((b1 - 0.25).abs() < 1e-6 && (b2 - 0.25).abs() < 1e-6);
        // Beyond corner b.
        assert_eq!(
            closest_point_on_triangle(Vec3::new(2.0, -1.0, 1.0), a, b, c).0,
            b
        );
        // Beside the hypotenuse.
        let (q, b1, b2) = closest_point_on_triangle(Vec3::new(1.0, 1.0, 0.0), a, b, c);
        assert!(q.distance(Vec3::new(0.5, 0.5, 0.0)) < 1e-6);
        assert!((b1 - 0.5).abs() < 1e-6 && (b2 - 0.5).abs() < 1e-6);
        // Below edge ab.
        let (q, _, b2) = closest_point_on_triangle(Vec3::new(0.3, -2.0, -1.0), a, b, c);
        assert!(q.distance(Vec3::new(0.3, 0.0, 0.0)) < 1e-6 && b2 == 0.0);
    }

    #[test]
    fn degenerate_triangles_answer_on_their_segment() {
        let (a, b, c) = (Vec3::ZERO, Vec3::X * 2.0, Vec3::X);
        let (q, b1, b2) = closest_point_on_triangle(Vec3::new(1.5, 1.0, 0.0), a, b, c);
        assert!(q.distance(Vec3::new(1.5, 0.0, 0.0)) < 1e-6, "{q}");
        let at = a * (1.0 - b1 - b2) + b * b1 + c * b2;
        assert!(at.distance(q) < 1e-5);
        let p = Vec3::new(3.0, 4.0, 5.0);
        assert_eq!(closest_point_on_triangle(p, a, a, a).0, a);
    }

    proptest! {
        /// The answer lies on the triangle (its barycentrics are a convex
        /// combination that reproduces it) and no point of the triangle is
        /// closer: not its corners, not points sampled on it.
        #[test]
        fn nothing_on_the_triangle_is_closer(
            p in v3(), a in v3(), b in v3(), c in v3(),
            samples in proptest::collection::vec((0.0f32..1.0, 0.0f32..1.0), 32),
        ) {
            let (q, b1, b2) = closest_point_on_triangle(p, a, b, c);
            prop_assert!(b1 >= 0.0 && b2 >= 0.0 && b1 + b2 <= 1.0 + 1e-5, "{b1} {b2}");
            let at = a * (1.0 - b1 - b2) + b * b1 + c * b2;
            let scale = 1.0 + a.abs().max_element() + b.abs().max_element() + c.abs().max_element();
            prop_assert!(at.distance(q) <= 1e-4 * scale, "{at} {q}");
            let d = p.distance(q);
            let tol = 1e-4 * (scale + p.abs().max_element());
            for (u, v) in samples {
                let (u, v) = if u + v > 1.0 { (1.0 - u, 1.0 - v) } else { (u, v) };
                let s = a * (1.0 - u - v) + b * u + c * v;
                prop_assert!(d <= p.distance(s) + tol, "{d} > {}", p.distance(s));
            }
            for corner in [a, b, c] {
                prop_assert!(d <= p.distance(corner) + tol);
            }
        }
    }
}
