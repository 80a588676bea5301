//! The scene: a closed room and objects on its floor, each one parry3d shape with an
//! isometry; exact ray casting, point-to-surface distances, shading, and the JSON
//! description (`gt/scene.json`) it is rebuilt from.

use std::fmt;
use std::path::Path;

use parry3d::math::{Isometry, Point, Vector};
use parry3d::na::{self, Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::query::Ray;
use parry3d::shape::SharedShape;
use serde::{Deserialize, Serialize};

use crate::classes::{
    self, BED, BOOKSHELF, CABINET, CEILING, CHAIR, FLOOR, LAMP, SOFA, TABLE, WALL,
};
use crate::config::Config;
use crate::error::{Result, SynthError};
use crate::rng::{tag, Rng};

mod layout;
mod shapes;
mod trace;

use layout::*;
pub use shapes::*;
pub use trace::Hit;
use trace::*;

/// Thickness of the slabs that bound the room (floor, ceiling, walls), metres.
pub const SLAB: f64 = 0.1;

/// Direction toward the fixed light (unnormalised), world frame.
const LIGHT: [f64; 3] = [0.35, 0.25, 1.0];
/// Ambient share of the Lambert shading.
const AMBIENT: f64 = 0.45;

/// A built scene: the objects and their parry3d shapes, ready for ray casting.
pub struct Scene {
    /// Inner size of the room (x, y, z), metres; the room spans
    /// [−x/2, x/2] × [−y/2, y/2] × [0, z].
    pub room_size: [f64; 3],
    /// The objects: the six room surfaces first (floor, ceiling, four walls), then the
    /// objects on the floor.
    pub objects: Vec<ObjectSpec>,
    placed: Vec<Placed>,
    light: [f64; 3],
}

impl fmt::Debug for Scene {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scene")
            .field("room_size", &self.room_size)
            .field("objects", &self.objects.len())
            .finish_non_exhaustive()
    }
}

/// The part of `gt/scene.json` that describes the geometry.
#[derive(Debug, Clone, Deserialize)]
struct Geometry {
    room: RoomJson,
    objects: Vec<ObjectSpec>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct RoomJson {
    pub size: [f64; 3],
    pub slab_thickness: f64,
}

impl Scene {
    /// Builds the shapes of a list of objects. Errors name the first invalid object.
    pub fn new(room_size: [f64; 3], objects: Vec<ObjectSpec>) -> Result<Scene> {
        let bad = |detail: String| SynthError::Scene {
            path: "<memory>".into(),
            detail,
        };
        let mut placed = Vec::with_capacity(objects.len());
        for (i, o) in objects.iter().enumerate() {
            if o.index as usize != i {
                return Err(bad(format!("object {i} has index {}", o.index)));
            }
            if !o.translation.iter().chain([&o.yaw]).all(|v| v.is_finite()) {
                return Err(bad(format!(
                    "object {i} ({}) has a non-finite pose",
                    o.name
                )));
            }
            let shape = o
                .shape
                .parry()
                .map_err(|e| bad(format!("object {i} ({}): {e}", o.name)))?;
            let pose = o.pose();
            let full =
                Isometry3::from_parts(pose.translation, pose.rotation * o.shape.base_rotation());
            let iso: Isometry<f32> = na::convert(full);
            let bs = shape.compute_bounding_sphere(&iso);
            let c = bs.center();
            let cull_box = matches!(o.shape, ShapeSpec::Chair { .. }).then(|| {
                let b = shape.compute_local_aabb();
                let pad = 1e-3;
                let lo = [b.mins.x, b.mins.y, b.mins.z].map(|v| f64::from(v) - pad);
                let hi = [b.maxs.x, b.maxs.y, b.maxs.z].map(|v| f64::from(v) + pad);
                (lo, hi)
            });
            // The f32-rounded dimensions parry uses, so both agree exactly.
            let f = |v: f64| f64::from(v as f32);
            let quadric = match o.shape {
                ShapeSpec::Ball { radius } => Some(Quadric::Ball(f(radius))),
                ShapeSpec::Capsule {
                    half_height,
                    radius,
                } => Some(Quadric::CapsuleX(f(half_height), f(radius))),
                ShapeSpec::Cylinder {
                    half_height,
                    radius,
                } => Some(Quadric::CylinderY(f(half_height), f(radius))),
                _ => None,
            };
            placed.push(Placed {
                full,
                cull_box,
                quadric,
                center: [f64::from(c.x), f64::from(c.y), f64::from(c.z)],
                radius: f64::from(bs.radius()) * 1.001 + 1e-4,
                shape,
                iso,
                pose,
            });
        }
        Ok(Scene {
            room_size,
            objects,
            placed,
            light: normalize(LIGHT),
        })
    }

    /// Generates the room and places `config.objects` objects by seeded rejection
    /// sampling (fewer if the floor is full).
    pub fn generate(config: &Config) -> Result<Scene> {
        let room = config.resolved_room();
        let mut objects = room_objects(room, config.seed);
        objects.extend(place_objects(config, room, objects.len() as u32));
        Scene::new(room, objects)
    }

    /// Rebuilds the scene from a `gt/scene.json` written by the generator.
    pub fn from_json(path: impl AsRef<Path>) -> Result<Scene> {
        let path = path.as_ref();
        let text =
            std::fs::read_to_string(path).map_err(crate::error::io_err(path, "cannot read"))?;
        Scene::from_json_str(&text).map_err(|e| match e {
            SynthError::Scene { detail, .. } => SynthError::Scene {
                path: path.display().to_string(),
                detail,
            },
            SynthError::Json { source, .. } => SynthError::Json {
                path: path.display().to_string(),
                source,
            },
            other => other,
        })
    }

    /// Rebuilds the scene from the text of a `gt/scene.json`.
    pub fn from_json_str(text: &str) -> Result<Scene> {
        let g: Geometry = serde_json::from_str(text).map_err(|source| SynthError::Json {
            path: "<memory>".into(),
            source,
        })?;
        Scene::new(g.room.size, g.objects)
    }

    pub(crate) fn room_json(&self) -> RoomJson {
        RoomJson {
            size: self.room_size,
            slab_thickness: SLAB,
        }
    }

    /// Number of objects (room surfaces included).
    pub fn len(&self) -> usize {
        self.objects.len()
    }

    /// Whether there are no objects.
    pub fn is_empty(&self) -> bool {
        self.objects.is_empty()
    }

    /// Nearest hit of the ray `origin + t·dir`, t >= 0 (dir need not be unit length; t is
    /// in units of its length). Shapes are solid: a ray starting inside one hits at t = 0.
    pub fn raycast(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<Hit> {
        self.raycast_within(origin, dir, f64::INFINITY)
    }

    /// Nearest hit with t < `max_t` (in units of `dir`'s length).
    pub fn raycast_within(&self, origin: [f64; 3], dir: [f64; 3], max_t: f64) -> Option<Hit> {
        let len = norm(dir);
        if !(len > 0.0 && len.is_finite() && origin.iter().all(|v| v.is_finite())) {
            return None;
        }
        let d = scale(dir, 1.0 / len);
        let ray = Ray::new(
            Point::new(origin[0] as f32, origin[1] as f32, origin[2] as f32),
            Vector::new(d[0] as f32, d[1] as f32, d[2] as f32),
        );
        let mut best = max_t * len;
        let mut found: Option<(usize, [f64; 3])> = None;
        for (i, p) in self.placed.iter().enumerate() {
            let oc = sub(p.center, origin);
            let tca = dot(oc, d);
            let d2 = dot(oc, oc) - tca * tca;
            let r2 = p.radius * p.radius;
            if d2 > r2 {
                continue;
            }
            let thc = (r2 - d2).sqrt();
            if tca + thc < 0.0 || tca - thc > best || !p.box_may_hit(origin, d, best) {
                continue;
            }
            if let Some((t, n)) = p.cast(&ray, origin, d, best) {
                best = t;
                found = Some((i, n));
            }
        }
        let (i, mut n) = found?;
        let nl = norm(n);
        n = if nl > 0.0 && nl.is_finite() {
            scale(n, 1.0 / nl)
        } else {
            scale(d, -1.0)
        };
        if dot(n, d) > 0.0 {
            n = scale(n, -1.0);
        }
        Some(Hit {
            t: best / len,
            object: i as u32,
            normal: n,
            point: add(origin, scale(d, best)),
        })
    }

    /// Distance from a point to the nearest surface of any object (room surfaces
    /// included), from parry3d's exact point projections (f32 precision, ~1e-6 m).
    pub fn distance_to_surface(&self, p: [f64; 3]) -> f64 {
        let pt = Point3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        self.placed
            .iter()
            .map(|o| {
                let proj = o.shape.project_point(&o.iso, &pt, false).point;
                let q = [f64::from(proj.x), f64::from(proj.y), f64::from(proj.z)];
                norm(sub(p, q))
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// The colour seen at a hit: base colour × texture × Lambert (fixed directional light
    /// plus ambient), 8-bit sRGB values (no gamma: the synthetic world is "already sRGB").
    pub fn shade(&self, hit: &Hit) -> [u8; 3] {
        let (o, p) = (
            &self.objects[hit.object as usize],
            &self.placed[hit.object as usize],
        );
        let local =
            p.pose
                .inverse_transform_point(&Point3::new(hit.point[0], hit.point[1], hit.point[2]));
        let tex = o.texture.factor([local.x, local.y, local.z]);
        let lambert = AMBIENT + (1.0 - AMBIENT) * dot(hit.normal, self.light).max(0.0);
        o.color
            .map(|c| (f64::from(c) * tex * lambert).round().clamp(0.0, 255.0) as u8)
    }

    pub(crate) fn pose(&self, i: usize) -> &Isometry3<f64> {
        &self.placed[i].pose
    }
}

// Small vector helpers on [f64; 3].
pub(crate) fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
pub(crate) fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    if n > 0.0 {
        scale(a, 1.0 / n)
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(shape: ShapeSpec, translation: [f64; 3], yaw: f64) -> Scene {
        let o = ObjectSpec {
            index: 0,
            name: "x".into(),
            class_id: 3,
            class_name: "cabinet".into(),
            room: false,
            shape,
            translation,
            yaw,
            color: [100, 100, 100],
            texture: Texture::Plain,
        };
        match Scene::new([10.0, 10.0, 3.0], vec![o]) {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn cylinder_is_upright_and_exact() {
        let s = one(
            ShapeSpec::Cylinder {
                half_height: 0.4,
                radius: 0.5,
            },
            [0.0, 0.0, 0.4],
            0.3,
        );
        // From above: hits the top cap at z = 0.8.
        let h = s.raycast([0.1, 0.1, 3.0], [0.0, 0.0, -1.0]);
        let h = h.map(|h| (h.t, h.normal));
        assert!(
            matches!(h, Some((t, n)) if (t - 2.2).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5),
            "{h:?}"
        );
        // From the side at height 0.2: hits the mantle at x = -0.5.
        let h = s.raycast([-3.0, 0.0, 0.2], [2.0, 0.0, 0.0]).map(|h| h.t);
        assert!(matches!(h, Some(t) if (t - 1.25).abs() < 1e-5), "{h:?}");
        assert!((s.distance_to_surface([0.0, 0.0, 1.8]) - 1.0).abs() < 1e-5);
        assert!((s.distance_to_surface([0.0, 0.0, 0.5]) - 0.3).abs() < 1e-5);
    }

    #[test]
    fn chair_mesh_is_closed_and_l_shaped() {
        let s = one(
            ShapeSpec::Chair {
                width: 0.5,
                depth: 0.5,
                seat_height: 0.45,
                back_height: 0.9,
                back_thickness: 0.1,
            },
            [0.0, 0.0, 0.0],
            0.0,
        );
        // Above the seat: hits z = 0.45; above the back: z = 0.9.
        let seat = s
            .raycast([0.1, 0.0, 2.0], [0.0, 0.0, -1.0])
            .map(|h| h.point[2]);
        let back = s
            .raycast([-0.2, 0.0, 2.0], [0.0, 0.0, -1.0])
            .map(|h| h.point[2]);
        assert!(
            matches!(seat, Some(z) if (z - 0.45).abs() < 1e-5),
            "{seat:?}"
        );
        assert!(
            matches!(back, Some(z) if (z - 0.9).abs() < 1e-5),
            "{back:?}"
        );
        // From the front at height 0.7: passes over the seat, hits the back's front face.
        let h = s
            .raycast([2.0, 0.0, 0.7], [-1.0, 0.0, 0.0])
            .map(|h| (h.point[0], h.normal[0]));
        assert!(
            matches!(h, Some((x, n)) if (x + 0.15).abs() < 1e-5 && n > 0.99),
            "{h:?}"
        );
        let Some(q) = (ShapeSpec::Chair {
            width: 0.5,
            depth: 0.5,
            seat_height: 0.45,
            back_height: 0.9,
            back_thickness: 0.1,
        })
        .quads() else {
            panic!("chair has quads")
        };
        // Closed: the outward-weighted face areas sum to zero.
        let mut sum = [0.0; 3];
        for quad in &q {
            let a = cross(quad.u, quad.v);
            let a = if dot(a, quad.n) < 0.0 {
                scale(a, -1.0)
            } else {
                a
            };
            sum = add(sum, a);
        }
        assert!(norm(sum) < 1e-12, "{sum:?}");
    }

    #[test]
    fn footprints_overlap_test() {
        let a = Footprint {
            c: [0.0, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        let b = Footprint {
            c: [2.05, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        assert!(!a.overlaps(&b, 0.0));
        assert!(a.overlaps(&b, 0.1));
        let c = Footprint {
            c: [1.6, 1.0],
            h: [0.5, 0.5],
            yaw: std::f64::consts::FRAC_PI_4,
        };
        assert!(!a.overlaps(&c, 0.0));
    }
}
