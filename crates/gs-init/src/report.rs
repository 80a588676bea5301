//! What an initialisation did, as counts that add up.

use serde::Serialize;

use crate::geometry::Reason;
use crate::params::Params;

/// Rejected points by the first gate they failed (gate order: non-finite, behind camera,
/// reprojection, angle).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Rejected {
    /// The DLT solution is not finite or at infinity.
    pub non_finite: u64,
    /// Camera z <= near in either view.
    pub behind_camera: u64,
    /// Reprojection error above the tolerance in either view.
    pub reprojection: u64,
    /// Triangulation angle below the minimum.
    pub low_angle: u64,
    /// The sum of the above.
    pub total: u64,
}

impl Rejected {
    /// Counts one rejection.
    pub fn add(&mut self, reason: Reason) {
        match reason {
            Reason::NonFinite => self.non_finite += 1,
            Reason::BehindCamera => self.behind_camera += 1,
            Reason::Reprojection => self.reprojection += 1,
            Reason::LowAngle => self.low_angle += 1,
        }
        self.total += 1;
    }

    /// Adds another tally.
    pub fn merge(&mut self, o: &Rejected) {
        self.non_finite += o.non_finite;
        self.behind_camera += o.behind_camera;
        self.reprojection += o.reprojection;
        self.low_angle += o.low_angle;
        self.total += o.total;
    }

    /// The count of one reason.
    pub fn get(&self, reason: Reason) -> u64 {
        match reason {
            Reason::NonFinite => self.non_finite,
            Reason::BehindCamera => self.behind_camera,
            Reason::Reprojection => self.reprojection,
            Reason::LowAngle => self.low_angle,
        }
    }
}

/// One reference view's share of the work.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReferenceReport {
    /// The reference view.
    pub view: usize,
    /// The views its matches were triangulated against, nearest pose first (dense), or
    /// in pair order (sparse).
    pub neighbours: Vec<usize>,
    /// Matches above the certainty threshold (dense: grid cells confident in at least
    /// one neighbour).
    pub confident: u64,
    /// Matches sampled from them (at most the budget).
    pub sampled: u64,
    /// Points kept.
    pub kept: u64,
}

/// The counts of an initialisation. `sampled = triangulated + rejected.non_finite` and
/// `triangulated = kept + rejected.behind_camera + rejected.reprojection +
/// rejected.low_angle`, so `sampled = kept + rejected.total`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// `dense` (matches) or `sparse` (sparse_matches).
    pub mode: &'static str,
    /// Views in the cameras file.
    pub views: usize,
    /// Ordered pairs in the matches file.
    pub pairs: usize,
    /// Pairs triangulated against (reference, neighbour).
    pub pairs_used: usize,
    /// Per reference view, in view order.
    pub references: Vec<ReferenceReport>,
    /// Confident matches over all references.
    pub confident: u64,
    /// Matches sampled (one point each).
    pub sampled: u64,
    /// Sampled matches with a finite triangulation.
    pub triangulated: u64,
    /// Two-view DLT solves (a dense sample is solved against every confident neighbour).
    pub dlt_solves: u64,
    /// Rejections by reason.
    pub rejected: Rejected,
    /// Gaussians written.
    pub kept: u64,
    /// Median over kept points of the larger reprojection error of the two views, pixels
    /// (null when none is kept).
    pub median_reproj_px: Option<f64>,
    /// Median triangulation angle of the kept points, degrees.
    pub median_angle_deg: Option<f64>,
    /// Median initial scale σ of the kept points, scene units.
    pub median_scale: Option<f64>,
    /// The parameters used.
    pub params: Params,
}

/// Median of a list (mean of the middle two for even lengths); `None` when empty.
pub(crate) fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_unstable_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    })
}
