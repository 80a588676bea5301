//! [`Params`] flat: every parameter one key, as in the pipeline's `[gs_init]` TOML
//! section and on the `gs-init` tool's command line (with the `clap` feature); the scale
//! rule is its text form (`pixels:1`, `distance:0.0005`, `knn:3`, see [`Scale`]'s
//! `FromStr`). The key names are written here only. ([`Params`]' own serde form, a JSON
//! object with a tagged scale, is what the gaussians file's `gs_init_params` metadata
//! records.)

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::params::{Params, Scale};

/// The defaults, for the command-line help.
#[cfg(feature = "clap")]
fn d() -> Params {
    Params::default()
}

/// Every parameter of [`Params`] as one flat key (see [`Params`] for the meanings and
/// the defaults).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct FlatParams {
    /// Reference views chosen by k-means over camera poses (dense matches only).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().references, help_heading = "Parameters"))]
    pub references: usize,
    /// Neighbours per reference by pose distance, among views it has pairs with (dense only).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().neighbours, help_heading = "Parameters"))]
    pub neighbours: usize,
    /// A match is confident when its certainty is above this.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().certainty_threshold, help_heading = "Parameters"))]
    pub certainty_threshold: f64,
    /// Confident matches sampled per reference view.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().budget, help_heading = "Parameters"))]
    pub budget: usize,
    /// Seed of the reference k-means and of the sampling.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().seed, help_heading = "Parameters"))]
    pub seed: u64,
    /// Largest reprojection error in pixels accepted in each of the two views.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().max_reproj_px, help_heading = "Parameters"))]
    pub max_reproj_px: f64,
    /// Smallest angle in degrees between the two viewing rays at the point.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().min_angle_deg, help_heading = "Parameters"))]
    pub min_angle_deg: f64,
    /// A point needs camera z > near in both views (scene units).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().near, help_heading = "Parameters"))]
    pub near: f64,
    /// Initial scale rule: `pixels[:P]` (σ = P reference pixels at the point's depth,
    /// P = 1 by default), `distance[:F]` (σ = F × distance to the reference camera, EDGS:
    /// F = 0.0005) or `knn[:K]` (σ = RMS distance to the K nearest Gaussians, 3DGS: K = 3).
    #[serde(serialize_with = "scale_as_text", deserialize_with = "scale_from_text")]
    #[cfg_attr(
        feature = "clap",
        arg(long, default_value_t = d().scale, value_name = "RULE", help_heading = "Parameters")
    )]
    pub scale: Scale,
}

impl Default for FlatParams {
    fn default() -> Self {
        Params::default().into()
    }
}

impl From<FlatParams> for Params {
    fn from(f: FlatParams) -> Params {
        Params {
            references: f.references,
            neighbours: f.neighbours,
            certainty_threshold: f.certainty_threshold,
            budget: f.budget,
            seed: f.seed,
            max_reproj_px: f.max_reproj_px,
            min_angle_deg: f.min_angle_deg,
            near: f.near,
            scale: f.scale,
        }
    }
}

impl From<Params> for FlatParams {
    fn from(p: Params) -> FlatParams {
        FlatParams {
            references: p.references,
            neighbours: p.neighbours,
            certainty_threshold: p.certainty_threshold,
            budget: p.budget,
            seed: p.seed,
            max_reproj_px: p.max_reproj_px,
            min_angle_deg: p.min_angle_deg,
            near: p.near,
            scale: p.scale,
        }
    }
}

impl fmt::Display for Scale {
    /// `pixels:P`, `distance:F` or `knn:K`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Scale::Pixels { pixels } => write!(f, "pixels:{pixels}"),
            Scale::Distance { factor } => write!(f, "distance:{factor}"),
            Scale::Knn { k } => write!(f, "knn:{k}"),
        }
    }
}

impl FromStr for Scale {
    type Err = String;

    /// `pixels[:P]` (P = 1), `distance[:F]` (F = 0.0005, EDGS) or `knn[:K]` (K = 3, 3DGS).
    fn from_str(s: &str) -> Result<Scale, String> {
        let (mode, value) = match s.split_once(':') {
            Some((m, v)) => (m, Some(v)),
            None => (s, None),
        };
        let number = |default: f64| -> Result<f64, String> {
            value.map_or(Ok(default), |v| {
                v.parse::<f64>()
                    .map_err(|e| format!("`{v}` is not a number: {e}"))
            })
        };
        Ok(match mode {
            "pixels" => Scale::Pixels {
                pixels: number(1.0)?,
            },
            "distance" => Scale::Distance {
                factor: number(0.0005)?,
            },
            "knn" => Scale::Knn {
                k: value.map_or(Ok(3), |v| {
                    v.parse::<usize>()
                        .map_err(|e| format!("`{v}` is not a count: {e}"))
                })?,
            },
            other => {
                return Err(format!(
                    "unknown scale rule `{other}`: expected pixels[:P], distance[:F] or knn[:K]"
                ))
            }
        })
    }
}

fn scale_as_text<S: Serializer>(scale: &Scale, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(scale)
}

fn scale_from_text<'de, D: Deserializer<'de>>(d: D) -> Result<Scale, D::Error> {
    let text = String::deserialize(d)?;
    text.parse().map_err(serde::de::Error::custom)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn scale_rules_round_trip_through_text() {
        for (text, scale) in [
            ("pixels:1", Scale::Pixels { pixels: 1.0 }),
            ("distance:0.0005", Scale::Distance { factor: 0.0005 }),
            ("knn:3", Scale::Knn { k: 3 }),
        ] {
            assert_eq!(text.parse::<Scale>().unwrap(), scale);
            assert_eq!(scale.to_string(), text);
        }
        assert_eq!("knn".parse::<Scale>().unwrap(), Scale::Knn { k: 3 });
        assert_eq!(
            "distance".parse::<Scale>().unwrap(),
            Scale::Distance { factor: 0.0005 }
        );
        let e = "huge".parse::<Scale>().unwrap_err();
        assert!(e.contains("pixels[:P]"), "{e}");
        assert!("knn:x".parse::<Scale>().is_err());
    }

    #[test]
    fn flat_params_round_trip() {
        let p = Params {
            scale: Scale::Knn { k: 5 },
            budget: 7,
            ..Params::default()
        };
        assert_eq!(Params::from(FlatParams::from(p)), p);
        assert_eq!(Params::from(FlatParams::default()), Params::default());
    }
}
