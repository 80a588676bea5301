//! The labelled triangle mesh of the scene (ScanNet-style ground truth).

use parry3d::na::Point3;
use parry3d::shape::{Ball, Capsule, Cylinder};
use profuse_formats::Mesh;

use crate::scene::{add, scale, Quad, Scene, ShapeSpec};

/// Mesh buffers before conversion to the file type.
#[derive(Default)]
struct Builder {
    vertices: Vec<[f32; 3]>,
    colors: Vec<[u8; 3]>,
    faces: Vec<[u32; 3]>,
    labels: Vec<u32>,
    instances: Vec<u32>,
}

impl Builder {
    fn push(
        &mut self,
        verts: &[[f64; 3]],
        faces: &[[u32; 3]],
        color: [u8; 3],
        label: u32,
        instance: u32,
    ) {
        let base = self.vertices.len() as u32;
        self.vertices
            .extend(verts.iter().map(|v| v.map(|x| x as f32)));
        self.colors.extend(std::iter::repeat_n(color, verts.len()));
        self.labels.extend(std::iter::repeat_n(label, verts.len()));
        self.instances
            .extend(std::iter::repeat_n(instance, verts.len()));
        self.faces.extend(faces.iter().map(|f| f.map(|i| base + i)));
    }
}

/// Subdivides a rectangle into a grid with edges no longer than `spacing`.
fn grid(q: &Quad, spacing: f64) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let len = |a: [f64; 3]| (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let nu = ((len(q.u) / spacing).ceil() as usize).clamp(1, 100_000);
    let nv = ((len(q.v) / spacing).ceil() as usize).clamp(1, 100_000);
    let mut verts = Vec::with_capacity((nu + 1) * (nv + 1));
    for j in 0..=nv {
        for i in 0..=nu {
            let p = add(
                q.o,
                add(
                    scale(q.u, i as f64 / nu as f64),
                    scale(q.v, j as f64 / nv as f64),
                ),
            );
            verts.push(p);
        }
    }
    let c = crate::scene::cross(q.u, q.v);
    let ccw = crate::scene::dot(c, q.n) > 0.0;
    let id = |i: usize, j: usize| (j * (nu + 1) + i) as u32;
    let mut faces = Vec::with_capacity(2 * nu * nv);
    for j in 0..nv {
        for i in 0..nu {
            let (a, b, cc, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            if ccw {
                faces.push([a, b, cc]);
                faces.push([a, cc, d]);
            } else {
                faces.push([a, cc, b]);
                faces.push([a, d, cc]);
            }
        }
    }
    (verts, faces)
}

fn subdiv(length: f64, spacing: f64, min: u32) -> u32 {
    ((length / spacing).ceil() as u32).clamp(min, 1024)
}

/// Triangulates every object in world coordinates: planar faces (room surfaces, boxes,
/// the chair) as grids with edges <= `spacing`, curved shapes with parry3d's
/// `to_trimesh` at a comparable subdivision. Room surfaces contribute only their inner
/// faces. Labels are NYU40 class ids, instances object index + 1, colours the base
/// colours.
pub(crate) fn build(scene: &Scene, spacing: f64) -> Mesh {
    let mut b = Builder::default();
    let [lx, ly, lz] = scene.room_size;
    let (hx, hy) = (lx / 2.0, ly / 2.0);
    for (i, o) in scene.objects.iter().enumerate() {
        let (verts, faces): (Vec<[f64; 3]>, Vec<[u32; 3]>) = if o.room {
            // The inner face of the slab, directly in world coordinates.
            let q = match o.name.as_str() {
                "floor" => Quad {
                    o: [-hx, -hy, 0.0],
                    u: [lx, 0.0, 0.0],
                    v: [0.0, ly, 0.0],
                    n: [0.0, 0.0, 1.0],
                },
                "ceiling" => Quad {
                    o: [-hx, -hy, lz],
                    u: [lx, 0.0, 0.0],
                    v: [0.0, ly, 0.0],
                    n: [0.0, 0.0, -1.0],
                },
                "wall_east" => Quad {
                    o: [hx, -hy, 0.0],
                    u: [0.0, ly, 0.0],
                    v: [0.0, 0.0, lz],
                    n: [-1.0, 0.0, 0.0],
                },
                "wall_west" => Quad {
                    o: [-hx, -hy, 0.0],
                    u: [0.0, ly, 0.0],
                    v: [0.0, 0.0, lz],
                    n: [1.0, 0.0, 0.0],
                },
                "wall_north" => Quad {
                    o: [-hx, hy, 0.0],
                    u: [lx, 0.0, 0.0],
                    v: [0.0, 0.0, lz],
                    n: [0.0, -1.0, 0.0],
                },
                _ => Quad {
                    o: [-hx, -hy, 0.0],
                    u: [lx, 0.0, 0.0],
                    v: [0.0, 0.0, lz],
                    n: [0.0, 1.0, 0.0],
                },
            };
            grid(&q, spacing)
        } else {
            let (local, faces) = local_mesh(&o.shape, spacing);
            let pose = scene.pose(i);
            let world = local
                .iter()
                .map(|p| {
                    let w = pose.transform_point(&Point3::new(p[0], p[1], p[2]));
                    [w.x, w.y, w.z]
                })
                .collect();
            (world, faces)
        };
        b.push(&verts, &faces, o.color, o.class_id, o.index + 1);
    }
    Mesh {
        vertices: b.vertices.into(),
        colors: Some(b.colors.into()),
        faces: Some(b.faces.into()),
        labels: Some(b.labels.into()),
        instances: Some(b.instances.into()),
        extra: [
            ("label_space".to_string(), "nyu40".to_string()),
            (
                "source".to_string(),
                format!("synth {} ground truth", env!("CARGO_PKG_VERSION")),
            ),
        ]
        .into_iter()
        .collect(),
    }
}

/// Vertices (object-local frame, z up) and faces of one object.
fn local_mesh(shape: &ShapeSpec, spacing: f64) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    if let Some(quads) = shape.quads() {
        let mut verts = Vec::new();
        let mut faces = Vec::new();
        for q in &quads {
            let (v, f) = grid(q, spacing);
            let base = verts.len() as u32;
            verts.extend(v);
            faces.extend(f.iter().map(|t| t.map(|i| base + i)));
        }
        return (verts, faces);
    }
    let tau = std::f64::consts::TAU;
    let (pts, faces) = match shape {
        ShapeSpec::Ball { radius } => {
            let r = *radius;
            Ball::new(r as f32).to_trimesh(
                subdiv(tau * r, spacing, 12),
                subdiv(tau * r / 2.0, spacing, 6),
            )
        }
        ShapeSpec::Capsule {
            half_height,
            radius,
        } => {
            let r = *radius;
            // parry applies the capsule's own axis (x here).
            Capsule::new_x(*half_height as f32, r as f32).to_trimesh(
                subdiv(tau * r, spacing, 12),
                subdiv(tau * r / 4.0, spacing, 4),
            )
        }
        ShapeSpec::Cylinder {
            half_height,
            radius,
        } => Cylinder::new(*half_height as f32, *radius as f32).to_trimesh(subdiv(
            tau * radius,
            spacing,
            12,
        )),
        _ => (Vec::new(), Vec::new()),
    };
    let verts = pts
        .iter()
        .map(|p| {
            let (x, y, z) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
            match shape {
                // Cylinder: parry y axis → our z axis (rotation about x by +90°).
                ShapeSpec::Cylinder { .. } => [x, -z, y],
                _ => [x, y, z],
            }
        })
        .collect();
    (verts, faces)
}
