//! The settings of the pose refinement ([`super::irls`]) and their
//! checks.

use serde::{Deserialize, Serialize};

use super::PoseError;

/// The default standard deviation of the start's translation, as a share
/// of the diagonal of the mesh's bounding box (chosen on the LM-O
/// development objects: 5%, 7% and 10% gave 7.18, 7.34 and 8.08 mm).
pub const START_SIGMA_DIAGONAL: f64 = 0.05;
/// The largest search range (pixels each way).
pub(super) const MAX_RANGE: usize = 200;

/// Settings of the refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IrlsParams {
    /// Outer iterations (fresh correspondences) at most.
    pub max_iterations: usize,
    /// Gauss-Newton steps per set of correspondences.
    pub inner_steps: usize,
    /// Pixels between samples along a projected edge.
    pub sample_step: f64,
    /// Search range along the normal, in pixels each way, at the first
    /// iteration; it shrinks by 30% per iteration down to a quarter of it
    /// (coarse to fine: far edges pull early, near ones decide late).
    pub search_range: f64,
    /// Smallest gradient magnitude (0..255 intensity per pixel) of a match.
    pub min_gradient: f64,
    /// Largest angle (degrees) between an image gradient and the normal.
    pub max_angle_degrees: f64,
    /// Smallest dihedral angle (degrees) of a crease edge.
    pub crease_degrees: f64,
    /// Tukey constant, in robust standard deviations.
    pub tukey_c: f64,
    /// Converged when an iteration moves the model's points by less than
    /// this in the image (pixels, at the object's depth).
    pub tolerance_px: f64,
    /// A Gauss-Newton step moves the model's points by at most this many
    /// pixels (longer steps are shortened): a trust region.
    pub max_step_px: f64,
    /// OR-IRLS keeps a correspondence when its sample and its match lie
    /// within this many pixels of the visibility mask (edges lie on the
    /// mask's border).
    pub mask_margin_px: usize,
    /// Restarts turn the initial pose this many degrees (and multiples, see
    /// `restart_rings`) either way about each camera axis (0: none); see
    /// [`restart_poses`].
    pub restart_degrees: f64,
    /// Rings of turned restarts: at `restart_degrees`, twice that, ...
    pub restart_rings: usize,
    /// Restarts move the initial pose this share of its distance nearer
    /// and farther (0: none).
    pub restart_depth: f64,
    /// The start pose's uncertainty as a MAP prior: standard deviation of
    /// its rotation, degrees (0: no prior on the rotation).
    pub start_sigma_degrees: f64,
    /// Standard deviation of its translation, in mesh units (0: no prior
    /// on the translation); `None`: [`START_SIGMA_DIAGONAL`] of the
    /// diagonal of the mesh's bounding box. Each part of the prior is on
    /// or off by itself.
    #[serde(default)]
    pub start_sigma_translation: Option<f64>,
    /// Edge samples per independent measurement: neighbouring samples of
    /// one outline share their errors (the same wrong edge), so the data
    /// term's information is divided by this against the prior.
    pub sample_correlation: f64,
    /// Weight of the region (colour) evidence of the outline against the
    /// edges (0: edges only); see [`super::region`].
    #[serde(default = "default_region_weight")]
    pub region_weight: f64,
}

fn default_region_weight() -> f64 {
    IrlsParams::default().region_weight
}

impl Default for IrlsParams {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            inner_steps: 3,
            sample_step: 3.0,
            search_range: 30.0,
            min_gradient: 8.0,
            max_angle_degrees: 30.0,
            crease_degrees: 30.0,
            tukey_c: 4.685,
            tolerance_px: 0.5,
            max_step_px: 4.0,
            mask_margin_px: 3,
            restart_degrees: 10.0,
            restart_rings: 1,
            restart_depth: 0.02,
            start_sigma_degrees: 5.0,
            start_sigma_translation: None,
            sample_correlation: 8.0,
            region_weight: 1.0,
        }
    }
}

/// The most iterations a refinement may be asked for.
pub const MAX_ITERATIONS: usize = 1000;

impl IrlsParams {
    /// Checks every setting; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), PoseError> {
        let checks = [
            (
                "max_iterations",
                (1..=MAX_ITERATIONS).contains(&self.max_iterations),
            ),
            ("inner_steps", self.inner_steps >= 1),
            (
                "sample_step",
                self.sample_step.is_finite() && self.sample_step >= 0.5,
            ),
            (
                "search_range",
                self.search_range.is_finite()
                    && self.search_range > 0.0
                    && self.search_range <= MAX_RANGE as f64,
            ),
            ("min_gradient", self.min_gradient.is_finite()),
            (
                "max_angle_degrees",
                (0.0..90.0).contains(&self.max_angle_degrees),
            ),
            (
                "crease_degrees",
                (0.0..180.0).contains(&self.crease_degrees),
            ),
            ("tukey_c", self.tukey_c > 0.0),
            ("tolerance_px", self.tolerance_px > 0.0),
            ("max_step_px", self.max_step_px > 0.0),
            ("mask_margin_px", self.mask_margin_px <= 50),
            (
                "restart_degrees",
                (0.0..=45.0).contains(&self.restart_degrees),
            ),
            ("restart_rings", self.restart_rings <= 4),
            ("restart_depth", (0.0..0.5).contains(&self.restart_depth)),
            (
                "start_sigma_degrees",
                self.start_sigma_degrees.is_finite() && self.start_sigma_degrees >= 0.0,
            ),
            (
                "start_sigma_translation",
                self.start_sigma_translation
                    .is_none_or(|v| v.is_finite() && v >= 0.0),
            ),
            (
                "sample_correlation",
                self.sample_correlation.is_finite() && self.sample_correlation >= 1.0,
            ),
            (
                "region_weight",
                self.region_weight.is_finite() && self.region_weight >= 0.0,
            ),
        ];
        match checks.iter().find(|(_, ok)| !ok) {
            None => Ok(()),
            Some((name, _)) => Err(PoseError::InvalidParameter(format!(
                "the pose refinement setting {name} is out of its range"
            ))),
        }
    }
}
