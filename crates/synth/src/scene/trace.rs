//! Ray casting against one placed object: its parry3d shape, or the exact interval of its
//! analytic quadric, and the hit with its normal and colour.

use super::*;

/// A ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter of the hit in units of the direction's length: point = origin + t·dir.
    pub t: f64,
    /// Index of the object hit.
    pub object: u32,
    /// Unit surface normal at the hit, facing the ray's origin.
    pub normal: [f64; 3],
    /// The hit point, world coordinates.
    pub point: [f64; 3],
}

pub(super) struct Placed {
    pub(super) shape: SharedShape,
    pub(super) iso: Isometry<f32>,
    pub(super) pose: Isometry3<f64>,
    pub(super) center: [f64; 3],
    pub(super) radius: f64,
    /// Pose of the parry shape's own frame (the object pose times the base rotation).
    pub(super) full: Isometry3<f64>,
    /// For the chair mesh (a BVH traversal): the local box, a cheap exact-miss test
    /// before the cast.
    pub(super) cull_box: Option<([f64; 3], [f64; 3])>,
    /// Quadrics cast analytically in f64 (parry's GJK ray cast for capsules and cylinders
    /// is only accurate to about a millimetre).
    pub(super) quadric: Option<Quadric>,
}

/// Shapes with a closed-form ray intersection, in the parry shape's own frame.
#[derive(Debug, Clone, Copy)]
pub(super) enum Quadric {
    /// Ball of radius r at the origin.
    Ball(f64),
    /// Capsule: segment (−h, 0, 0)–(h, 0, 0), radius r.
    CapsuleX(f64, f64),
    /// Cylinder: axis y, |y| <= h, radius r.
    CylinderY(f64, f64),
}

/// Entry and exit parameters of a unit ray with a ball at `c` of radius `r`.
pub(super) fn ball_interval(o: [f64; 3], d: [f64; 3], c: [f64; 3], r: f64) -> Option<(f64, f64)> {
    let oc = sub(o, c);
    let b = dot(oc, d);
    let cc = dot(oc, oc) - r * r;
    let disc = b * b - cc;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    // Numerically stable roots.
    let q = if b > 0.0 { -b - s } else { -b + s };
    let (t0, t1) = if q != 0.0 { (cc / q, q) } else { (-b, -b) };
    Some((t0.min(t1), t0.max(t1)))
}

/// Entry and exit of a unit ray with the infinite cylinder of radius r around the axis
/// `axis` (0 = x, 1 = y) through the origin; `None` if it misses. A ray parallel to the
/// axis gives an infinite interval when inside.
pub(super) fn tube_interval(o: [f64; 3], d: [f64; 3], axis: usize, r: f64) -> Option<(f64, f64)> {
    let (i, j) = if axis == 0 { (1, 2) } else { (0, 2) };
    let a = d[i] * d[i] + d[j] * d[j];
    let b = o[i] * d[i] + o[j] * d[j];
    let c = o[i] * o[i] + o[j] * o[j] - r * r;
    if a < 1e-18 {
        return (c <= 0.0).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let disc = b * b - a * c;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let q = if b > 0.0 { -b - s } else { -b + s };
    let (t0, t1) = if q != 0.0 {
        (c / q, q / a)
    } else {
        (-b / a, -b / a)
    };
    Some((t0.min(t1), t0.max(t1)))
}

impl Quadric {
    /// First t >= 0 where the unit ray (local frame) enters the solid (0 if it starts
    /// inside), and the outward normal there.
    pub(super) fn cast(self, o: [f64; 3], d: [f64; 3]) -> Option<(f64, [f64; 3])> {
        match self {
            Quadric::Ball(r) => {
                let (t0, t1) = ball_interval(o, d, [0.0; 3], r)?;
                if t1 < 0.0 {
                    return None;
                }
                let t = t0.max(0.0);
                Some((t, normalize(add(o, scale(d, t)))))
            }
            Quadric::CapsuleX(h, r) => {
                // The union of a finite tube and two end balls: the entry is the earliest
                // entry of the three (the tube's flat ends lie inside the balls).
                let mut best: Option<(f64, f64)> = None;
                let mut take = |iv: Option<(f64, f64)>| {
                    if let Some((t0, t1)) = iv {
                        if t1 >= 0.0 && best.is_none_or(|b| t0 < b.0) {
                            best = Some((t0, t1));
                        }
                    }
                };
                if let Some((t0, t1)) = tube_interval(o, d, 0, r) {
                    // Restrict the tube to |x| <= h.
                    let (s0, s1) = if d[0].abs() < 1e-18 {
                        if o[0].abs() <= h {
                            (f64::NEG_INFINITY, f64::INFINITY)
                        } else {
                            (1.0, -1.0)
                        }
                    } else {
                        let (a, b) = ((-h - o[0]) / d[0], (h - o[0]) / d[0]);
                        (a.min(b), a.max(b))
                    };
                    let (e0, e1) = (t0.max(s0), t1.min(s1));
                    if e0 <= e1 {
                        take(Some((e0, e1)));
                    }
                }
                take(ball_interval(o, d, [-h, 0.0, 0.0], r));
                take(ball_interval(o, d, [h, 0.0, 0.0], r));
                let (t0, _) = best?;
                let t = t0.max(0.0);
                let p = add(o, scale(d, t));
                let n = normalize([p[0] - p[0].clamp(-h, h), p[1], p[2]]);
                Some((t, n))
            }
            Quadric::CylinderY(h, r) => {
                let (t0, t1) = tube_interval(o, d, 1, r)?;
                let (s0, s1) = if d[1].abs() < 1e-18 {
                    if o[1].abs() > h {
                        return None;
                    }
                    (f64::NEG_INFINITY, f64::INFINITY)
                } else {
                    let (a, b) = ((-h - o[1]) / d[1], (h - o[1]) / d[1]);
                    (a.min(b), a.max(b))
                };
                let (e0, e1) = (t0.max(s0), t1.min(s1));
                if e0 > e1 || e1 < 0.0 {
                    return None;
                }
                let t = e0.max(0.0);
                let p = add(o, scale(d, t));
                let n = if s0 >= t0 {
                    [0.0, p[1].signum(), 0.0]
                } else {
                    normalize([p[0], 0.0, p[2]])
                };
                Some((t, n))
            }
        }
    }
}

impl Placed {
    /// Whether the ray (unit `d`) can hit the local box before `best`.
    pub(super) fn box_may_hit(&self, o: [f64; 3], d: [f64; 3], best: f64) -> bool {
        let Some((lo, hi)) = &self.cull_box else {
            return true;
        };
        let (o, d) = self.to_local(o, d);
        let (mut t0, mut t1) = (0.0f64, best);
        for k in 0..3 {
            if d[k].abs() < 1e-12 {
                if o[k] < lo[k] || o[k] > hi[k] {
                    return false;
                }
                continue;
            }
            let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
            if t0 > t1 {
                return false;
            }
        }
        true
    }

    /// A world ray in the parry shape's frame.
    pub(super) fn to_local(&self, o: [f64; 3], d: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let lo = self
            .full
            .inverse_transform_point(&Point3::new(o[0], o[1], o[2]));
        let ld = self
            .full
            .inverse_transform_vector(&Vector3::new(d[0], d[1], d[2]));
        ([lo.x, lo.y, lo.z], [ld.x, ld.y, ld.z])
    }

    /// Nearest hit (t along the unit world ray, world normal) before `best`.
    pub(super) fn cast(
        &self,
        ray: &Ray,
        o: [f64; 3],
        d: [f64; 3],
        best: f64,
    ) -> Option<(f64, [f64; 3])> {
        if let Some(q) = self.quadric {
            let (lo, ld) = self.to_local(o, d);
            let (t, n) = q.cast(lo, ld)?;
            let n = self.full.transform_vector(&Vector3::new(n[0], n[1], n[2]));
            return (t < best).then_some((t, [n.x, n.y, n.z]));
        }
        let max_toi = if best.is_finite() {
            best as f32
        } else {
            f32::MAX
        };
        let inter = self
            .shape
            .cast_ray_and_get_normal(&self.iso, ray, max_toi, true)?;
        let t = f64::from(inter.time_of_impact);
        let n = inter.normal;
        (t < best).then_some((t, [f64::from(n.x), f64::from(n.y), f64::from(n.z)]))
    }
}
