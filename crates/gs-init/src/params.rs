//! Parameters, defaulting to the paper's (EDGS's) values where it has them.

use serde::Serialize;

use crate::error::{InitError, Result};
use crate::geometry::Gates;

/// How the isotropic initial scale (standard deviation σ) of a Gaussian is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "mode", rename_all = "snake_case")]
pub enum Scale {
    /// σ = `pixels` × z / f: the size of `pixels` reference-view pixels at the point's
    /// depth z (camera z in the reference view, f its mean focal length). Proportional to
    /// depth like EDGS's rule, but independent of the image resolution.
    Pixels {
        /// Footprint in reference pixels.
        pixels: f64,
    },
    /// σ = `factor` × distance from the reference camera centre (EDGS: 0.0005).
    Distance {
        /// Multiplier of the distance.
        factor: f64,
    },
    /// σ = sqrt(mean squared distance to the `k` nearest other initial Gaussians), at
    /// least sqrt(1e-7) (the 3DGS initialisation with k = 3, via a kiddo k-d tree).
    Knn {
        /// Neighbours averaged.
        k: usize,
    },
}

impl Default for Scale {
    fn default() -> Self {
        Scale::Pixels { pixels: 1.0 }
    }
}

/// Parameters of an initialisation. `Default` gives the paper's values (EDGS, which the
/// paper's initialisation follows) and this crate's documented choices where the paper
/// leaves them open.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Params {
    /// Reference views chosen by k-means over camera poses (dense matches only; EDGS: 180).
    pub references: usize,
    /// Neighbours per reference by pose distance, among the views it has match pairs with
    /// (dense matches only; EDGS: 3).
    pub neighbours: usize,
    /// A match is confident when its certainty is above this (EDGS on RoMa: 0.05).
    pub certainty_threshold: f64,
    /// Confident matches sampled per reference view (EDGS: 15,000).
    pub budget: usize,
    /// Seed of the k-means and of the sampling.
    pub seed: u64,
    /// Largest reprojection error in pixels accepted in each of the two views (2 px).
    pub max_reproj_px: f64,
    /// Smallest angle between the two viewing rays, degrees (2°: at 2° a one-pixel error
    /// moves the point by about 3% of its depth at f = 1000 px).
    pub min_angle_deg: f64,
    /// A point needs camera z > `near` in both views, scene units (0.2, the rasterizer's
    /// near plane, so that every kept Gaussian renders in the views that made it).
    pub near: f64,
    /// The initial scale rule.
    pub scale: Scale,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            references: 180,
            neighbours: 3,
            certainty_threshold: 0.05,
            budget: 15_000,
            seed: 0,
            max_reproj_px: 2.0,
            min_angle_deg: 2.0,
            near: 0.2,
            scale: Scale::default(),
        }
    }
}

impl Params {
    /// The gates of the triangulation.
    pub fn gates(&self) -> Gates {
        Gates {
            max_reproj_px: self.max_reproj_px,
            min_angle_deg: self.min_angle_deg,
            near: self.near,
        }
    }

    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<()> {
        let bad = |name, value: String, expected| {
            Err(InitError::Param {
                name,
                value,
                expected,
            })
        };
        if self.references == 0 {
            return bad("references", "0".into(), "at least 1");
        }
        if self.neighbours == 0 {
            return bad("neighbours", "0".into(), "at least 1");
        }
        if self.budget == 0 {
            return bad("budget", "0".into(), "at least 1");
        }
        if !(0.0..1.0).contains(&self.certainty_threshold) {
            return bad(
                "certainty_threshold",
                self.certainty_threshold.to_string(),
                "a value in [0, 1)",
            );
        }
        if !(self.max_reproj_px > 0.0 && self.max_reproj_px.is_finite()) {
            return bad(
                "max_reproj_px",
                self.max_reproj_px.to_string(),
                "a finite value > 0",
            );
        }
        if !(0.0..180.0).contains(&self.min_angle_deg) {
            return bad(
                "min_angle_deg",
                self.min_angle_deg.to_string(),
                "an angle in [0, 180)",
            );
        }
        if !(self.near >= 0.0 && self.near.is_finite()) {
            return bad("near", self.near.to_string(), "a finite value >= 0");
        }
        match self.scale {
            Scale::Pixels { pixels: v } | Scale::Distance { factor: v }
                if !(v > 0.0 && v.is_finite()) =>
            {
                bad("scale", v.to_string(), "a finite value > 0")
            }
            Scale::Knn { k: 0 } => bad("scale", "knn with k = 0".into(), "k >= 1"),
            _ => Ok(()),
        }
    }
}
