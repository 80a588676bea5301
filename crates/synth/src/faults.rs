//! Named fault sets: the fault models the accuracy sweep (`profuse sweep`) runs the
//! pipeline under, applied on top of a preset.

use crate::config::Config;
use crate::error::{Result, SynthError};

/// A named set of fault parameters, applied on top of a preset with [`FaultSet::apply`]
/// (`synth --faults NAME`; individual flags are applied after it and win).
///
/// Every set starts from [`FaultSet::Default`], which changes three feature parameters and
/// keeps the preset's mask faults (`min_area_px`, `p_miss_small`, `p_split` 0.15,
/// `p_merge` 0.1, `jitter_px`, `p_jitter`, `p_unassigned`, `wrong_class_beta`,
/// `text_noise`) and its views and matches:
///
/// | set | parameters |
/// |---|---|
/// | `default` | `feature_noise` 1.5, `p_wrong_class` 0.1, `crop_noise_px` 40000 |
/// | `noisy-features` | default + `feature_noise` 2.5, `p_wrong_class` 0.25 |
/// | `harsh-segmentation` | default + `p_split` 0.35, `p_merge` 0.3 |
/// | `sparse-views` | default + `views` 12, `warp_noise_px` 1.0, `outlier_frac` 0.1 |
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum FaultSet {
    /// What `profuse demo` uses: CLIP-like mask features with per-mask noise 1.5 (cosine
    /// to the class prototype about 0.55), 10% of masks pulled toward a wrong class, and
    /// noise growing as sqrt(40000 / area) for masks under 40,000 pixels (CLIP embeds
    /// small crops less reliably). The preset's own features are nearly noise-free, which
    /// leaves nothing for cross-view proposals to fix.
    Default,
    /// Default + `feature_noise` 2.5 and `p_wrong_class` 0.25: worse CLIP features.
    NoisyFeatures,
    /// Default + `p_split` 0.35 and `p_merge` 0.3: SAM over- and under-segments more.
    HarshSegmentation,
    /// Default + 12 views (instead of the preset's), `warp_noise_px` 1.0 and
    /// `outlier_frac` 0.1: fewer views, noisier dense matches.
    SparseViews,
}

impl FaultSet {
    /// Every set, in the order of [`FaultSet::NAMES`].
    pub const ALL: [FaultSet; 4] = [
        FaultSet::Default,
        FaultSet::NoisyFeatures,
        FaultSet::HarshSegmentation,
        FaultSet::SparseViews,
    ];

    /// The names [`FaultSet::parse`] accepts.
    pub const NAMES: [&'static str; 4] = [
        "default",
        "noisy-features",
        "harsh-segmentation",
        "sparse-views",
    ];

    /// The set's name (`default`, `noisy-features`, `harsh-segmentation`, `sparse-views`).
    pub fn name(self) -> &'static str {
        match self {
            FaultSet::Default => "default",
            FaultSet::NoisyFeatures => "noisy-features",
            FaultSet::HarshSegmentation => "harsh-segmentation",
            FaultSet::SparseViews => "sparse-views",
        }
    }

    /// Parses [`FaultSet::name`].
    pub fn parse(name: &str) -> Result<FaultSet> {
        FaultSet::ALL
            .into_iter()
            .find(|f| f.name() == name)
            .ok_or_else(|| SynthError::FaultSet(name.to_string()))
    }

    /// Sets the set's parameters in `config` (see the table on [`FaultSet`]); every other
    /// parameter keeps its value.
    pub fn apply(self, config: &mut Config) {
        let f = &mut config.faults;
        f.feature_noise = 1.5;
        f.p_wrong_class = 0.1;
        f.crop_noise_px = 40_000.0;
        match self {
            FaultSet::Default => {}
            FaultSet::NoisyFeatures => {
                f.feature_noise = 2.5;
                f.p_wrong_class = 0.25;
            }
            FaultSet::HarshSegmentation => {
                f.p_split = 0.35;
                f.p_merge = 0.3;
            }
            FaultSet::SparseViews => {
                config.views = 12;
                config.warp_noise_px = 1.0;
                config.outlier_frac = 0.1;
            }
        }
    }

    /// A preset's configuration with this set applied.
    pub fn config(self, preset: crate::Preset, seed: u64) -> Config {
        let mut c = Config::preset(preset, seed);
        self.apply(&mut c);
        c
    }
}

impl std::fmt::Display for FaultSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Preset;

    #[test]
    fn names_round_trip_and_unknown_names_are_errors() {
        for (set, name) in FaultSet::ALL.into_iter().zip(FaultSet::NAMES) {
            assert_eq!(set.name(), name);
            assert_eq!(FaultSet::parse(name).ok(), Some(set));
        }
        let e = FaultSet::parse("noisy").err().map(|e| e.to_string());
        assert!(e.is_some_and(|e| e.contains("noisy") && e.contains("sparse-views")));
    }

    #[test]
    fn every_set_changes_exactly_its_documented_parameters() {
        let preset = Config::preset(Preset::Demo, 4);
        let mut default = preset.clone();
        default.faults.feature_noise = 1.5;
        default.faults.p_wrong_class = 0.1;
        default.faults.crop_noise_px = 40_000.0;
        assert_eq!(FaultSet::Default.config(Preset::Demo, 4), default);

        let mut noisy = default.clone();
        noisy.faults.feature_noise = 2.5;
        noisy.faults.p_wrong_class = 0.25;
        assert_eq!(FaultSet::NoisyFeatures.config(Preset::Demo, 4), noisy);

        let mut harsh = default.clone();
        harsh.faults.p_split = 0.35;
        harsh.faults.p_merge = 0.3;
        assert_eq!(FaultSet::HarshSegmentation.config(Preset::Demo, 4), harsh);

        let mut sparse = default.clone();
        sparse.views = 12;
        sparse.warp_noise_px = 1.0;
        sparse.outlier_frac = 0.1;
        assert_eq!(FaultSet::SparseViews.config(Preset::Demo, 4), sparse);
        for set in FaultSet::ALL {
            assert!(set.config(Preset::Demo, 0).validate().is_ok(), "{set}");
            assert!(set.config(Preset::Tiny, 0).validate().is_ok(), "{set}");
        }
    }
}
