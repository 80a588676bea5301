//! The room's layout: its six surface slabs and the furniture sampled per class and placed
//! without overlaps.

use super::*;

/// The six room surfaces: floor, ceiling, walls east (+x), west (−x), north (+y),
/// south (−y). Slabs outside the room's inner box, so rays from inside hit their inner
/// faces.
pub(super) fn room_objects(room: [f64; 3], seed: u64) -> Vec<ObjectSpec> {
    let [lx, ly, lz] = room;
    let (hx, hy, hz, t) = (lx / 2.0, ly / 2.0, lz / 2.0, SLAB / 2.0);
    let mut rng = Rng::new(&[seed, tag::LAYOUT, 0]);
    let mut wall_color = || {
        let j = rng.range(-12.0, 12.0);
        [
            (205.0 + j) as u8,
            (198.0 + j * 0.8) as u8,
            (182.0 + j * 0.5) as u8,
        ]
    };
    // (name, class, centre, half extents, colour, texture)
    type Slab = (&'static str, u32, [f64; 3], [f64; 3], [u8; 3], Texture);
    // A wall: striped along `axis`.
    let wall = |name, centre, half, color, axis| -> Slab {
        let texture = Texture::Stripes {
            period: 0.4,
            axis,
            contrast: 0.12,
        };
        (name, WALL, centre, half, color, texture)
    };
    let slabs: [Slab; 6] = [
        (
            "floor",
            FLOOR,
            [0.0, 0.0, -t],
            [hx + SLAB, hy + SLAB, t],
            [170, 120, 80],
            Texture::Checker {
                size: 0.5,
                contrast: 0.35,
            },
        ),
        (
            "ceiling",
            CEILING,
            [0.0, 0.0, lz + t],
            [hx + SLAB, hy + SLAB, t],
            [238, 236, 230],
            Texture::Plain,
        ),
        wall(
            "wall_east",
            [hx + t, 0.0, hz],
            [t, hy + SLAB, hz + SLAB],
            wall_color(),
            1,
        ),
        wall(
            "wall_west",
            [-hx - t, 0.0, hz],
            [t, hy + SLAB, hz + SLAB],
            wall_color(),
            1,
        ),
        wall(
            "wall_north",
            [0.0, hy + t, hz],
            [hx + SLAB, t, hz + SLAB],
            wall_color(),
            0,
        ),
        wall(
            "wall_south",
            [0.0, -hy - t, hz],
            [hx + SLAB, t, hz + SLAB],
            wall_color(),
            0,
        ),
    ];
    slabs
        .into_iter()
        .enumerate()
        .map(
            |(i, (name, class_id, translation, half, color, texture))| ObjectSpec {
                index: i as u32,
                name: name.to_string(),
                class_id,
                class_name: profuse_formats::label_space::nyu40_name(class_id)
                    .unwrap_or("unknown")
                    .to_string(),
                room: true,
                shape: ShapeSpec::Cuboid { half_extents: half },
                translation,
                yaw: 0.0,
                color,
                texture,
            },
        )
        .collect()
}

/// Rounds to f32 precision so that the JSON round trip rebuilds identical shapes.
pub(super) fn r32(v: f64) -> f64 {
    f64::from(v as f32)
}

pub(super) fn sample_shape(class: u32, rng: &mut Rng) -> ShapeSpec {
    let mut u = |lo: f64, hi: f64| r32(rng.range(lo, hi));
    match class {
        CABINET => ShapeSpec::Cuboid {
            half_extents: [u(0.3, 0.6), u(0.22, 0.35), u(0.35, 0.6)],
        },
        BED => ShapeSpec::Cuboid {
            half_extents: [u(0.95, 1.1), u(0.7, 0.9), u(0.22, 0.3)],
        },
        CHAIR => ShapeSpec::Chair {
            width: u(0.45, 0.55),
            depth: u(0.45, 0.55),
            seat_height: u(0.42, 0.5),
            back_height: u(0.85, 1.0),
            back_thickness: u(0.07, 0.12),
        },
        SOFA => ShapeSpec::Capsule {
            half_height: u(0.55, 0.85),
            radius: u(0.33, 0.42),
        },
        TABLE => ShapeSpec::Cylinder {
            half_height: u(0.33, 0.4),
            radius: u(0.35, 0.55),
        },
        BOOKSHELF => ShapeSpec::Cuboid {
            half_extents: [u(0.35, 0.55), u(0.14, 0.2), u(0.75, 1.0)],
        },
        _ => ShapeSpec::Ball {
            radius: u(0.15, 0.28),
        },
    }
}

pub(super) fn class_color(class: u32) -> [f64; 3] {
    match class {
        CABINET => [150.0, 100.0, 60.0],
        BED => [70.0, 110.0, 185.0],
        CHAIR => [200.0, 60.0, 50.0],
        SOFA => [60.0, 150.0, 80.0],
        TABLE => [195.0, 160.0, 95.0],
        BOOKSHELF => [125.0, 80.0, 145.0],
        LAMP => [245.0, 215.0, 70.0],
        _ => [128.0, 128.0, 128.0],
    }
}

pub(super) fn sample_texture(rng: &mut Rng) -> Texture {
    match rng.below(5) {
        0 => Texture::Plain,
        1 | 2 => Texture::Checker {
            size: r32(rng.range(0.08, 0.2)),
            contrast: r32(rng.range(0.15, 0.3)),
        },
        _ => Texture::Stripes {
            period: r32(rng.range(0.06, 0.2)),
            axis: rng.below(3),
            contrast: r32(rng.range(0.15, 0.3)),
        },
    }
}

/// An oriented 2D box: centre, half sizes, yaw.
#[derive(Clone, Copy)]
pub(super) struct Footprint {
    pub(super) c: [f64; 2],
    pub(super) h: [f64; 2],
    pub(super) yaw: f64,
}

impl Footprint {
    pub(super) fn axes(&self) -> [[f64; 2]; 2] {
        let (s, c) = self.yaw.sin_cos();
        [[c, s], [-s, c]]
    }

    pub(super) fn corners(&self) -> [[f64; 2]; 4] {
        let [a, b] = self.axes();
        let mut out = [[0.0; 2]; 4];
        for (k, (sa, sb)) in [(1.0, 1.0), (1.0, -1.0), (-1.0, -1.0), (-1.0, 1.0)]
            .into_iter()
            .enumerate()
        {
            out[k] = [
                self.c[0] + sa * self.h[0] * a[0] + sb * self.h[1] * b[0],
                self.c[1] + sa * self.h[0] * a[1] + sb * self.h[1] * b[1],
            ];
        }
        out
    }

    /// Separating-axis test with `margin` added around both boxes.
    pub(super) fn overlaps(&self, other: &Footprint, margin: f64) -> bool {
        let d = [other.c[0] - self.c[0], other.c[1] - self.c[1]];
        let (aa, ba) = (self.axes(), other.axes());
        for axis in aa.iter().chain(ba.iter()) {
            let proj = |f: &Footprint, ax: &[[f64; 2]; 2]| {
                f.h[0] * (ax[0][0] * axis[0] + ax[0][1] * axis[1]).abs()
                    + f.h[1] * (ax[1][0] * axis[0] + ax[1][1] * axis[1]).abs()
            };
            let dist = (d[0] * axis[0] + d[1] * axis[1]).abs();
            if dist > proj(self, &aa) + proj(other, &ba) + margin {
                return false;
            }
        }
        true
    }
}

/// Semi-axes of the ellipse that object footprints must stay inside (a fraction of the
/// camera orbit, so cameras never stand inside or right next to an object).
pub(crate) fn placement_ellipse(config: &Config, room: [f64; 3]) -> [f64; 2] {
    let k = 0.75 * config.orbit_frac;
    [k * room[0] / 2.0, k * room[1] / 2.0]
}

pub(super) fn place_objects(config: &Config, room: [f64; 3], first_index: u32) -> Vec<ObjectSpec> {
    let mut rng = Rng::new(&[config.seed, tag::LAYOUT, 1]);
    // Classes: every furniture class once (shuffled), then random classes.
    let mut order = classes::FURNITURE.to_vec();
    for i in (1..order.len()).rev() {
        let j = rng.below(i + 1);
        order.swap(i, j);
    }
    let wanted: Vec<u32> = (0..config.objects)
        .map(|k| {
            if k < order.len() {
                order[k]
            } else {
                classes::FURNITURE[rng.below(classes::FURNITURE.len())]
            }
        })
        .collect();
    let mut candidates: Vec<(u32, ShapeSpec, [u8; 3], Texture)> = wanted
        .iter()
        .map(|&class| {
            let shape = sample_shape(class, &mut rng);
            let base = class_color(class);
            let color = base.map(|c| (c + rng.range(-25.0, 25.0)).round().clamp(0.0, 255.0) as u8);
            let texture = sample_texture(&mut rng);
            (class, shape, color, texture)
        })
        .collect();
    // Largest footprints first: rejection sampling succeeds more often.
    candidates.sort_by(|a, b| {
        let fa = a.1.footprint();
        let fb = b.1.footprint();
        (fb[0] * fb[1]).total_cmp(&(fa[0] * fa[1]))
    });
    let ell = placement_ellipse(config, room);
    let inside = |p: [f64; 2]| (p[0] / ell[0]).powi(2) + (p[1] / ell[1]).powi(2) <= 1.0;
    let mut placed: Vec<Footprint> = Vec::new();
    let mut out = Vec::new();
    let mut per_class = std::collections::BTreeMap::<u32, usize>::new();
    for (class, shape, color, texture) in candidates {
        // Up to 400 tries at full size, then at 85% and 70% of it; skipped if all fail.
        let mut spot = None;
        for shrink in [1.0, 0.85, 0.7] {
            let shape = shape.scaled(shrink);
            let h = shape.footprint();
            for _ in 0..400 {
                let f = Footprint {
                    c: [rng.range(-ell[0], ell[0]), rng.range(-ell[1], ell[1])],
                    h,
                    yaw: r32(rng.range(0.0, std::f64::consts::TAU)),
                };
                if f.corners().iter().all(|c| inside(*c))
                    && !placed.iter().any(|g| g.overlaps(&f, 0.12))
                {
                    spot = Some((f, shape));
                    break;
                }
            }
            if spot.is_some() {
                break;
            }
        }
        let Some((f, shape)) = spot else { continue };
        placed.push(f);
        let n = per_class.entry(class).or_default();
        let name = format!(
            "{}_{}",
            profuse_formats::label_space::nyu40_name(class).unwrap_or("object"),
            *n
        );
        *n += 1;
        out.push(ObjectSpec {
            index: first_index + out.len() as u32,
            name,
            class_id: class,
            class_name: profuse_formats::label_space::nyu40_name(class)
                .unwrap_or("unknown")
                .to_string(),
            room: false,
            translation: [r32(f.c[0]), r32(f.c[1]), shape.rest_height()],
            yaw: f.yaw,
            shape,
            color,
            texture,
        });
    }
    out
}
