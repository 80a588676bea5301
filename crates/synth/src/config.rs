//! Generator parameters: presets, the mask fault model, and validation.

use serde::{Deserialize, Serialize};

use crate::error::{Result, SynthError};

/// The seeded fault model that turns exact object regions into "SAM-like" masks with
/// "CLIP-like" features. Every decision is keyed by (seed, view, object) or
/// (seed, view, pixel), never by thread or iteration order. See the crate docs and the
/// README for the exact procedure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultModel {
    /// Regions with fewer pixels than this are "small" (candidates for being missed).
    pub min_area_px: u32,
    /// Probability that a small region is dropped (its pixels get no mask).
    pub p_miss_small: f64,
    /// Probability that a mask is split in two by a random line through its centroid
    /// (over-segmentation).
    pub p_split: f64,
    /// Probability that an object's region is merged with one neighbouring region
    /// (sharing a boundary) into one mask (under-segmentation).
    pub p_merge: f64,
    /// Width in pixels of the boundary band subject to jitter (Chebyshev distance).
    pub jitter_px: u32,
    /// Probability that a pixel within `jitter_px` of a mask boundary takes the label of
    /// a neighbouring region.
    pub p_jitter: f64,
    /// Probability that a boundary pixel (4-neighbour of another label) gets no mask.
    pub p_unassigned: f64,
    /// Scale of the Gaussian noise added to a mask feature: `feature_noise · g`,
    /// g ~ N(0, I/D) (so |g| ≈ 1).
    pub feature_noise: f64,
    /// Probability that a mask feature is biased toward a random other class.
    pub p_wrong_class: f64,
    /// Range [lo, hi] of the bias β of a wrong-class feature:
    /// normalize((1 − β)·p_c + β·p_other + noise).
    pub wrong_class_beta: [f64; 2],
    /// Scale of the noise of a class prompt embedding: normalize(p_c + text_noise · g).
    pub text_noise: f64,
    /// CLIP's embedding of a small crop is less reliable than of a large one: a mask of
    /// `a` pixels gets `feature_noise · sqrt(max(1, crop_noise_px / a))` instead of
    /// `feature_noise` (0 = off, every mask the same noise).
    #[serde(default)]
    pub crop_noise_px: f64,
}

impl Default for FaultModel {
    fn default() -> Self {
        FaultModel {
            min_area_px: 150,
            p_miss_small: 0.5,
            p_split: 0.15,
            p_merge: 0.1,
            jitter_px: 1,
            p_jitter: 0.3,
            p_unassigned: 0.1,
            feature_noise: 0.3,
            p_wrong_class: 0.05,
            wrong_class_beta: [0.3, 0.7],
            text_noise: 0.25,
            crop_noise_px: 0.0,
        }
    }
}

impl FaultModel {
    /// No faults: every fault probability 0, so masks equal the visible object regions
    /// exactly. Feature and text noise are kept.
    pub fn exact() -> Self {
        FaultModel {
            p_miss_small: 0.0,
            p_split: 0.0,
            p_merge: 0.0,
            p_jitter: 0.0,
            p_unassigned: 0.0,
            p_wrong_class: 0.0,
            ..FaultModel::default()
        }
    }

    fn validate(&self) -> Result<()> {
        for (name, p) in [
            ("p_miss_small", self.p_miss_small),
            ("p_split", self.p_split),
            ("p_merge", self.p_merge),
            ("p_jitter", self.p_jitter),
            ("p_unassigned", self.p_unassigned),
            ("p_wrong_class", self.p_wrong_class),
        ] {
            check(name, p, (0.0..=1.0).contains(&p), "a probability in [0, 1]")?;
        }
        check(
            "feature_noise",
            self.feature_noise,
            (0.0..=100.0).contains(&self.feature_noise),
            "a value in [0, 100]",
        )?;
        check(
            "crop_noise_px",
            self.crop_noise_px,
            self.crop_noise_px.is_finite() && self.crop_noise_px >= 0.0,
            "a finite value >= 0",
        )?;
        check(
            "text_noise",
            self.text_noise,
            (0.0..=100.0).contains(&self.text_noise),
            "a value in [0, 100]",
        )?;
        let [lo, hi] = self.wrong_class_beta;
        check(
            "wrong_class_beta",
            format!("[{lo}, {hi}]"),
            (0.0..=1.0).contains(&lo) && (0.0..=1.0).contains(&hi) && lo <= hi,
            "0 <= lo <= hi <= 1",
        )?;
        check(
            "jitter_px",
            self.jitter_px,
            self.jitter_px <= 16,
            "at most 16",
        )?;
        Ok(())
    }
}

/// Storage precision of the warp and certainty tensors of the matches file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MatchPrecision {
    /// F32 (exact projections; the default).
    F32,
    /// F16 (half the size; ~1e-3 in normalised coordinates, a fraction of a pixel
    /// below ~1000 px).
    F16,
}

/// The named presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Preset {
    /// 4 views at 64×48, 4 objects, D = 64: for unit tests (well under a second).
    Tiny,
    /// 24 views at 320×240, 10 objects of every class, D = 512, 20 000 GT Gaussians:
    /// the default scene of the quick start.
    Demo,
    /// Benchmark sizes, set by flags (defaults: 100 views at 640×480, 20 objects).
    Scale,
}

impl Preset {
    /// Parses `tiny`, `demo` or `scale`.
    pub fn parse(name: &str) -> Result<Preset> {
        match name {
            "tiny" => Ok(Preset::Tiny),
            "demo" => Ok(Preset::Demo),
            "scale" => Ok(Preset::Scale),
            other => Err(SynthError::Preset(other.to_string())),
        }
    }

    /// The preset's name.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Tiny => "tiny",
            Preset::Demo => "demo",
            Preset::Scale => "scale",
        }
    }
}

/// Everything that determines a generated scene. Two runs with equal configs write
/// byte-identical files, whatever the thread count.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// The preset the values started from (informational).
    pub preset: String,
    /// The seed of every random decision.
    pub seed: u64,
    /// Number of views (cameras on the orbit).
    pub views: usize,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Number of objects placed on the floor (besides the six room surfaces). Fewer are
    /// placed if the floor is full (reported as `objects_placed`).
    pub objects: usize,
    /// Room size (x, y, z) in metres; `None` = automatic: 10 × 8 × 3 m for up to 10
    /// objects, the floor scaled by sqrt(objects / 10) beyond.
    pub room_size: Option<[f64; 3]>,
    /// Horizontal field of view in degrees (fx = fy = (W/2) / tan(hfov/2)).
    pub hfov_deg: f64,
    /// Camera orbit: semi-axes as a fraction of the room's half extents.
    pub orbit_frac: f64,
    /// Camera height above the floor in metres (before jitter).
    pub camera_height: f64,
    /// Uniform jitter (±) of the camera height in metres.
    pub height_jitter: f64,
    /// Height of the look-at point near the room centre, metres.
    pub target_height: f64,
    /// Uniform jitter (±) of the look-at point in x, y, z, metres.
    pub target_jitter: f64,
    /// Feature dimension D of mask features and prompt embeddings.
    pub feature_dim: usize,
    /// Distractor prompt names (classes absent from the scene, own prototypes).
    pub distractors: Vec<String>,
    /// The mask fault model.
    pub faults: FaultModel,
    /// Write `masks.safetensors` (and `gt/mask_objects.json`).
    pub write_masks: bool,
    /// Write `matches.safetensors`.
    pub write_matches: bool,
    /// Match grid size as a fraction of the image size (0 < s <= 1).
    pub match_scale: f64,
    /// Nearest views (by camera-centre distance) paired with each view.
    pub neighbours: usize,
    /// Standard deviation in pixels of Gaussian noise added to warp targets.
    pub warp_noise_px: f64,
    /// Fraction of cells replaced by a random target with certainty in [0.5, 1].
    pub outlier_frac: f64,
    /// Precision of warp and certainty.
    pub match_precision: MatchPrecision,
    /// Every k-th view (0, k, 2k, ...) gets a LERF-style label file.
    pub eval_every: usize,
    /// Ground-truth Gaussians to sample (0 = no `gt/gaussians.safetensors`).
    pub gaussians: usize,
    /// Largest edge length in metres of the grids that triangulate planar faces (room
    /// surfaces, boxes, the chair) in `gt/mesh.safetensors`; curved shapes get a
    /// comparable subdivision.
    pub mesh_spacing: f64,
}

impl Config {
    /// The parameters of a preset with the given seed.
    pub fn preset(preset: Preset, seed: u64) -> Config {
        let base = Config {
            preset: preset.name().to_string(),
            seed,
            views: 24,
            width: 320,
            height: 240,
            objects: 10,
            room_size: None,
            hfov_deg: 60.0,
            orbit_frac: 0.8,
            camera_height: 1.6,
            height_jitter: 0.15,
            target_height: 0.5,
            target_jitter: 0.3,
            feature_dim: 512,
            distractors: vec!["guitar".into(), "banana".into(), "umbrella".into()],
            faults: FaultModel::default(),
            write_masks: true,
            write_matches: true,
            match_scale: 0.5,
            neighbours: 3,
            warp_noise_px: 0.0,
            outlier_frac: 0.0,
            match_precision: MatchPrecision::F32,
            eval_every: 5,
            gaussians: 20_000,
            mesh_spacing: 0.05,
        };
        match preset {
            Preset::Demo => base,
            Preset::Tiny => Config {
                views: 4,
                width: 64,
                height: 48,
                objects: 4,
                feature_dim: 64,
                eval_every: 2,
                gaussians: 0,
                mesh_spacing: 0.25,
                faults: FaultModel {
                    min_area_px: 12,
                    ..FaultModel::default()
                },
                ..base
            },
            Preset::Scale => Config {
                views: 100,
                width: 640,
                height: 480,
                objects: 20,
                eval_every: 10,
                gaussians: 100_000,
                mesh_spacing: 0.1,
                faults: FaultModel {
                    min_area_px: 600,
                    ..FaultModel::default()
                },
                ..base
            },
        }
    }

    /// The room size used: `room_size` or the automatic size for `objects`.
    pub fn resolved_room(&self) -> [f64; 3] {
        self.room_size.unwrap_or_else(|| {
            let s = (self.objects as f64 / 10.0).max(1.0).sqrt();
            [10.0 * s, 8.0 * s, 3.0]
        })
    }

    /// Match grid width and height.
    pub fn match_grid(&self) -> (usize, usize) {
        let w = (f64::from(self.width) * self.match_scale).round().max(1.0) as usize;
        let h = (f64::from(self.height) * self.match_scale).round().max(1.0) as usize;
        (w, h)
    }

    /// Checks every parameter; the error names the first one out of range.
    pub fn validate(&self) -> Result<()> {
        self.validate_views()?;
        self.validate_outputs()?;
        self.faults.validate()
    }

    /// [`Config::validate`] of the room, the objects, the views and their cameras, and the
    /// feature dimension.
    fn validate_views(&self) -> Result<()> {
        check(
            "views",
            self.views,
            (1..=100_000).contains(&self.views),
            "1 ..= 100000",
        )?;
        check(
            "width",
            self.width,
            (1..=16384).contains(&self.width),
            "1 ..= 16384",
        )?;
        check(
            "height",
            self.height,
            (1..=16384).contains(&self.height),
            "1 ..= 16384",
        )?;
        check(
            "objects",
            self.objects,
            self.objects <= 10_000,
            "at most 10000",
        )?;
        let room = self.resolved_room();
        check(
            "room_size",
            format!("{room:?}"),
            room.iter()
                .all(|v| v.is_finite() && *v >= 1.0 && *v <= 1000.0),
            "three sizes in [1, 1000] metres",
        )?;
        check(
            "hfov_deg",
            self.hfov_deg,
            self.hfov_deg > 1.0 && self.hfov_deg < 179.0,
            "in (1, 179) degrees",
        )?;
        check(
            "orbit_frac",
            self.orbit_frac,
            self.orbit_frac > 0.0 && self.orbit_frac < 1.0,
            "in (0, 1)",
        )?;
        check(
            "camera_height",
            self.camera_height,
            self.camera_height > 0.0 && self.camera_height + self.height_jitter < room[2],
            "> 0 and (with jitter) below the ceiling",
        )?;
        check(
            "height_jitter",
            self.height_jitter,
            self.height_jitter >= 0.0 && self.height_jitter < self.camera_height,
            ">= 0 and below camera_height",
        )?;
        check(
            "target_height",
            self.target_height,
            self.target_height.is_finite(),
            "a finite height",
        )?;
        check(
            "target_jitter",
            self.target_jitter,
            (0.0..=10.0).contains(&self.target_jitter),
            "in [0, 10]",
        )?;
        check(
            "feature_dim",
            self.feature_dim,
            (1..=65536).contains(&self.feature_dim),
            "1 ..= 65536",
        )
    }

    /// [`Config::validate`] of the prompts' distractors, the matches, the evaluation
    /// frames, the ground-truth Gaussians and the mesh.
    fn validate_outputs(&self) -> Result<()> {
        if let Some(bad) = self.distractors.iter().find(|d| d.is_empty()) {
            check("distractors", format!("{bad:?}"), false, "non-empty names")?;
        }
        check(
            "match_scale",
            self.match_scale,
            self.match_scale > 0.0 && self.match_scale <= 1.0,
            "in (0, 1]",
        )?;
        check(
            "neighbours",
            self.neighbours,
            self.neighbours <= 1000,
            "at most 1000",
        )?;
        check(
            "warp_noise_px",
            self.warp_noise_px,
            (0.0..=1e4).contains(&self.warp_noise_px),
            "in [0, 10000]",
        )?;
        check(
            "outlier_frac",
            self.outlier_frac,
            (0.0..=1.0).contains(&self.outlier_frac),
            "in [0, 1]",
        )?;
        check("eval_every", self.eval_every, self.eval_every >= 1, ">= 1")?;
        check(
            "gaussians",
            self.gaussians,
            self.gaussians <= 100_000_000,
            "at most 100000000",
        )?;
        check(
            "mesh_spacing",
            self.mesh_spacing,
            self.mesh_spacing >= 0.005 && self.mesh_spacing <= 100.0,
            "in [0.005, 100] metres",
        )
    }
}

fn check(name: &'static str, value: impl ToString, ok: bool, expected: &str) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(SynthError::Parameter {
            name,
            value: value.to_string(),
            expected: expected.to_string(),
        })
    }
}
