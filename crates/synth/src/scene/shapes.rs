//! What an object is: its shape (boxes, cylinders, spheres, furniture made of quads), its
//! surface texture and its pose and class.

use super::*;

/// The geometry of an object, in its local frame (see [`ObjectSpec`] for the pose).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ShapeSpec {
    /// A box centred at the local origin.
    Cuboid {
        /// Half sizes along local x, y, z.
        half_extents: [f64; 3],
    },
    /// A ball centred at the local origin.
    Ball {
        /// Radius.
        radius: f64,
    },
    /// A cylinder centred at the local origin, axis along local **z** (upright).
    Cylinder {
        /// Half of the axial length.
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// A capsule centred at the local origin, axis along local x (lying).
    Capsule {
        /// Half of the segment length (without the caps).
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// The chair: a closed triangle mesh with an L-shaped profile (seat block plus back),
    /// footprint centred at the local origin, standing on local z = 0, back at local
    /// x = −depth/2, extruded along local y.
    Chair {
        /// Size along local y.
        width: f64,
        /// Size along local x.
        depth: f64,
        /// Height of the seat's top face.
        seat_height: f64,
        /// Height of the back's top face.
        back_height: f64,
        /// Thickness of the back along local x.
        back_thickness: f64,
    },
}

impl ShapeSpec {
    /// Short name of the shape kind (`cuboid`, `ball`, `cylinder`, `capsule`, `chair`).
    pub fn kind(&self) -> &'static str {
        match self {
            ShapeSpec::Cuboid { .. } => "cuboid",
            ShapeSpec::Ball { .. } => "ball",
            ShapeSpec::Cylinder { .. } => "cylinder",
            ShapeSpec::Capsule { .. } => "capsule",
            ShapeSpec::Chair { .. } => "chair",
        }
    }

    /// Rotation from the parry shape's own frame to the object's local frame (parry's
    /// cylinder axis is y; ours is z).
    pub(super) fn base_rotation(&self) -> UnitQuaternion<f64> {
        match self {
            ShapeSpec::Cylinder { .. } => {
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2)
            }
            _ => UnitQuaternion::identity(),
        }
    }

    pub(super) fn dims(&self) -> Vec<f64> {
        match self {
            ShapeSpec::Cuboid { half_extents } => half_extents.to_vec(),
            ShapeSpec::Ball { radius } => vec![*radius],
            ShapeSpec::Cylinder {
                half_height,
                radius,
            }
            | ShapeSpec::Capsule {
                half_height,
                radius,
            } => {
                vec![*half_height, *radius]
            }
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => vec![*width, *depth, *seat_height, *back_height, *back_thickness],
        }
    }

    pub(super) fn check(&self) -> std::result::Result<(), String> {
        let d = self.dims();
        if !d.iter().all(|v| v.is_finite() && *v > 0.0 && *v < 1e4) {
            return Err(format!(
                "{} dimensions must be finite and in (0, 1e4), got {d:?}",
                self.kind()
            ));
        }
        if let ShapeSpec::Chair {
            depth,
            seat_height,
            back_height,
            back_thickness,
            ..
        } = self
        {
            if back_thickness >= depth || seat_height >= back_height {
                return Err(
                    "chair needs back_thickness < depth and seat_height < back_height".into(),
                );
            }
        }
        Ok(())
    }

    /// The planar faces of a box-like shape as rectangles in the local frame (`None` for
    /// curved shapes). Each is (corner, edge u, edge v, outward normal).
    pub(crate) fn quads(&self) -> Option<Vec<Quad>> {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => {
                Some(box_quads([-h[0], -h[1], -h[2]], [h[0], h[1], h[2]]))
            }
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => Some(chair_quads(
                *width,
                *depth,
                *seat_height,
                *back_height,
                *back_thickness,
            )),
            _ => None,
        }
    }

    /// The parry shape (in parry's own frame; see `base_rotation`).
    pub(super) fn parry(&self) -> std::result::Result<SharedShape, String> {
        self.check()?;
        let f = |v: f64| v as f32;
        Ok(match self {
            ShapeSpec::Cuboid { half_extents: h } => SharedShape::cuboid(f(h[0]), f(h[1]), f(h[2])),
            ShapeSpec::Ball { radius } => SharedShape::ball(f(*radius)),
            ShapeSpec::Cylinder {
                half_height,
                radius,
            } => SharedShape::cylinder(f(*half_height), f(*radius)),
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => SharedShape::capsule_x(f(*half_height), f(*radius)),
            ShapeSpec::Chair { .. } => {
                let quads = self.quads().unwrap_or_default();
                let mut vertices = Vec::with_capacity(quads.len() * 4);
                let mut indices = Vec::with_capacity(quads.len() * 2);
                for q in &quads {
                    let base = vertices.len() as u32;
                    for c in q.corners() {
                        vertices.push(Point::new(f(c[0]), f(c[1]), f(c[2])));
                    }
                    let [a, b] = q.triangles();
                    indices.push(a.map(|i| base + i));
                    indices.push(b.map(|i| base + i));
                }
                SharedShape::trimesh(vertices, indices).map_err(|e| format!("chair mesh: {e:?}"))?
            }
        })
    }

    /// The shape scaled by `s` (f32-rounded dimensions).
    pub(super) fn scaled(&self, s: f64) -> ShapeSpec {
        if s == 1.0 {
            return self.clone();
        }
        let f = |v: f64| r32(v * s);
        match self {
            ShapeSpec::Cuboid { half_extents: h } => ShapeSpec::Cuboid {
                half_extents: h.map(f),
            },
            ShapeSpec::Ball { radius } => ShapeSpec::Ball { radius: f(*radius) },
            ShapeSpec::Cylinder {
                half_height,
                radius,
            } => ShapeSpec::Cylinder {
                half_height: f(*half_height),
                radius: f(*radius),
            },
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => ShapeSpec::Capsule {
                half_height: f(*half_height),
                radius: f(*radius),
            },
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => ShapeSpec::Chair {
                width: f(*width),
                depth: f(*depth),
                seat_height: f(*seat_height),
                back_height: f(*back_height),
                back_thickness: f(*back_thickness),
            },
        }
    }

    /// 2D footprint half sizes (along local x, y) for non-overlap tests.
    pub(super) fn footprint(&self) -> [f64; 2] {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => [h[0], h[1]],
            ShapeSpec::Ball { radius } | ShapeSpec::Cylinder { radius, .. } => [*radius, *radius],
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => [half_height + radius, *radius],
            ShapeSpec::Chair { width, depth, .. } => [depth / 2.0, width / 2.0],
        }
    }

    /// Height of the local origin above the floor for an object resting on the floor.
    pub(super) fn rest_height(&self) -> f64 {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => h[2],
            ShapeSpec::Ball { radius } | ShapeSpec::Capsule { radius, .. } => *radius,
            ShapeSpec::Cylinder { half_height, .. } => *half_height,
            ShapeSpec::Chair { .. } => 0.0,
        }
    }
}

/// A rectangle: corner `o`, edges `u` and `v`, outward normal `n`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Quad {
    pub o: [f64; 3],
    pub u: [f64; 3],
    pub v: [f64; 3],
    pub n: [f64; 3],
}

impl Quad {
    pub(super) fn corners(&self) -> [[f64; 3]; 4] {
        let (o, u, v) = (self.o, self.u, self.v);
        [o, add(o, u), add(add(o, u), v), add(o, v)]
    }

    /// Two triangles over `corners()` with counter-clockwise winding seen from outside.
    pub(super) fn triangles(&self) -> [[u32; 3]; 2] {
        if dot(cross(self.u, self.v), self.n) > 0.0 {
            [[0, 1, 2], [0, 2, 3]]
        } else {
            [[0, 2, 1], [0, 3, 2]]
        }
    }
}

/// The six faces of an axis-aligned box [lo, hi].
pub(super) fn box_quads(lo: [f64; 3], hi: [f64; 3]) -> Vec<Quad> {
    let s = sub(hi, lo);
    let (ex, ey, ez) = ([s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]);
    vec![
        Quad {
            o: lo,
            u: ey,
            v: ez,
            n: [-1.0, 0.0, 0.0],
        },
        Quad {
            o: [hi[0], lo[1], lo[2]],
            u: ey,
            v: ez,
            n: [1.0, 0.0, 0.0],
        },
        Quad {
            o: lo,
            u: ex,
            v: ez,
            n: [0.0, -1.0, 0.0],
        },
        Quad {
            o: [lo[0], hi[1], lo[2]],
            u: ex,
            v: ez,
            n: [0.0, 1.0, 0.0],
        },
        Quad {
            o: lo,
            u: ex,
            v: ey,
            n: [0.0, 0.0, -1.0],
        },
        Quad {
            o: [lo[0], lo[1], hi[2]],
            u: ex,
            v: ey,
            n: [0.0, 0.0, 1.0],
        },
    ]
}

/// The closed L-shaped chair: profile in local (x, z), extruded along y. The profile is
/// cut into three rectangles (back below and above the seat height, seat) so that no
/// edge has a T-junction and the mesh is watertight.
pub(super) fn chair_quads(width: f64, depth: f64, seat: f64, back: f64, thick: f64) -> Vec<Quad> {
    let (x0, x1, x2) = (-depth / 2.0, -depth / 2.0 + thick, depth / 2.0);
    let (z0, z1, z2) = (0.0, seat, back);
    let (y0, y1) = (-width / 2.0, width / 2.0);
    let ey = [0.0, width, 0.0];
    let mut q = Vec::new();
    // Side faces (y = y0 and y = y1): the three profile rectangles.
    for (xa, xb, za, zb) in [(x0, x1, z0, z1), (x0, x1, z1, z2), (x1, x2, z0, z1)] {
        let u = [xb - xa, 0.0, 0.0];
        let v = [0.0, 0.0, zb - za];
        q.push(Quad {
            o: [xa, y0, za],
            u,
            v,
            n: [0.0, -1.0, 0.0],
        });
        q.push(Quad {
            o: [xa, y1, za],
            u,
            v,
            n: [0.0, 1.0, 0.0],
        });
    }
    // Faces along the profile outline, each spanning the width.
    let strip = |a: [f64; 2], b: [f64; 2], n: [f64; 2]| Quad {
        o: [a[0], y0, a[1]],
        u: [b[0] - a[0], 0.0, b[1] - a[1]],
        v: ey,
        n: [n[0], 0.0, n[1]],
    };
    q.push(strip([x0, z0], [x1, z0], [0.0, -1.0])); // bottom under the back
    q.push(strip([x1, z0], [x2, z0], [0.0, -1.0])); // bottom under the seat
    q.push(strip([x2, z0], [x2, z1], [1.0, 0.0])); // seat front
    q.push(strip([x1, z1], [x2, z1], [0.0, 1.0])); // seat top
    q.push(strip([x1, z1], [x1, z2], [1.0, 0.0])); // back, front face
    q.push(strip([x0, z2], [x1, z2], [0.0, 1.0])); // back top
    q.push(strip([x0, z0], [x0, z1], [-1.0, 0.0])); // back face, lower
    q.push(strip([x0, z1], [x0, z2], [-1.0, 0.0])); // back face, upper
    q
}

/// A procedural texture, evaluated in the object's local frame (for the room surfaces,
/// whose local frames are world-aligned, that is world coordinates up to a shift).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Texture {
    /// Uniform.
    Plain,
    /// 3D checkerboard of cell `size`; dark cells are darkened by `contrast`.
    Checker {
        /// Cell size, metres.
        size: f64,
        /// Darkening of the dark cells, in [0, 1).
        contrast: f64,
    },
    /// Stripes across local `axis` (0 = x, 1 = y, 2 = z) with the given `period`.
    Stripes {
        /// Stripe period (one dark + one light stripe is two periods), metres.
        period: f64,
        /// Local axis the stripes vary along.
        axis: usize,
        /// Darkening of the dark stripes, in [0, 1).
        contrast: f64,
    },
}

impl Texture {
    pub(super) fn factor(&self, p: [f64; 3]) -> f64 {
        // A small irrational offset keeps faces at round coordinates off cell borders.
        let cell = |x: f64, s: f64| ((x + 0.0137) / s).floor() as i64;
        match self {
            Texture::Plain => 1.0,
            Texture::Checker { size, contrast } => {
                let k = cell(p[0], *size) + cell(p[1], *size) + cell(p[2], *size);
                if k.rem_euclid(2) == 1 {
                    1.0 - contrast
                } else {
                    1.0
                }
            }
            Texture::Stripes {
                period,
                axis,
                contrast,
            } => {
                if cell(p[(*axis).min(2)], *period).rem_euclid(2) == 1 {
                    1.0 - contrast
                } else {
                    1.0
                }
            }
        }
    }
}

/// One object of the scene (room surfaces included): class, shape and pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectSpec {
    /// Object index = object id in `gt/views.safetensors`; mesh instance = index + 1.
    pub index: u32,
    /// Unique name, e.g. `floor`, `wall_east`, `chair_1`.
    pub name: String,
    /// NYU40 class id.
    pub class_id: u32,
    /// NYU40 class name.
    pub class_name: String,
    /// Whether this is a room surface (floor, ceiling, wall).
    pub room: bool,
    /// The geometry in the local frame.
    pub shape: ShapeSpec,
    /// World position of the local origin, metres.
    pub translation: [f64; 3],
    /// Rotation about the world z axis, radians. The world pose is
    /// `translation · Rz(yaw)`; the local frame's z is the world's z.
    pub yaw: f64,
    /// Base colour, sRGB 8 bit.
    pub color: [u8; 3],
    /// Procedural texture.
    pub texture: Texture,
}

impl ObjectSpec {
    /// The world pose of the local frame.
    pub fn pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(
                self.translation[0],
                self.translation[1],
                self.translation[2],
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw),
        )
    }

    /// The world rotation as a quaternion (w, x, y, z).
    pub fn rotation_wxyz(&self) -> [f64; 4] {
        let q = self.pose().rotation;
        [q.w, q.i, q.j, q.k]
    }
}
