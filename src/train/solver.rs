//! The 1-slack cutting-plane solver (Joachims, Finley and Yu 2009) of the
//! structural SVM, as its steps: search the cached locations for the most
//! violated outputs and add their plane while it is violated
//! ([`cached_rounds`]); a full search over every location finds new
//! violators ([`full_search`]), whose plane updates the working set and
//! the QP's solution ([`update`]) until none is violated by more than
//! `epsilon` ([`converged`]). The separation oracle is the detector's
//! loss-augmented search (`search.rs`); latent imputation, where boxes
//! train, happens between whole trainings (`multiview.rs`).

use std::time::Instant;

use indicatif::ProgressBar;

use crate::vision::detect::Detector;

use super::examples::Example;
use super::layout::Layout;
use super::qp::{Plane, WorkingSet};
use super::{search, Round, TrainError, TrainParams, TrainReport};

/// The solver's state: the working set of planes, the weights and slack
/// of its QP's last solution.
struct State {
    ws: WorkingSet,
    w: Vec<f64>,
    xi: f64,
    /// The weights constrained to be non-negative.
    nonneg: Vec<usize>,
}

impl State {
    /// How much `plane` is violated at the current weights.
    fn violation(&self, plane: &Plane) -> f64 {
        plane.b - dot(&plane.g, &self.w)
    }
}

/// Trains the weights of `layout` on `examples`: at most
/// `params.max_passes` full searches, each after at most
/// `params.max_inner` rounds over the cached locations. `report` gets the
/// figures of every step.
pub(super) fn cutting_plane(
    layout: &Layout,
    examples: &mut [Example],
    params: &TrainParams,
    label: &str,
    progress: &ProgressBar,
    report: &mut TrainReport,
) -> Result<Vec<f64>, TrainError> {
    let mut st = State {
        ws: WorkingSet::default(),
        w: vec![0.0; layout.len],
        xi: 0.0,
        nonneg: layout.nonneg(),
    };
    let mut approx_done = false;
    progress.set_length(params.solver.max_passes as u64);
    progress.set_position(0);
    for pass in 0..=params.solver.max_passes {
        // The first pass's cached rounds start from the seeds: the
        // initialisation.
        cached_rounds(&mut st, layout, examples, params, report)?;
        if pass == params.solver.max_passes {
            break;
        }
        // Budgeted searches mine hard examples cheaply while the weights
        // still move; exact ones decide convergence (or the mining search
        // does, without `exact_check`).
        let exact = pass >= params.solver.mining_passes || approx_done;
        let round = full_search(&st, layout, examples, params, exact, report)?;
        let viol = st.violation(&round.plane);
        progress.inc(1);
        progress.set_message(format!(
            "{label}: pass {} violation {viol:.4} slack {:.4} loss {:.3}",
            pass + 1,
            st.xi,
            round.loss
        ));
        if converged(viol, st.xi, params) {
            if exact || !params.solver.exact_check {
                report.converged = true;
                break;
            }
            approx_done = true;
            continue;
        }
        // An exact search that still found violations: mining goes on
        // (while its passes last), and the next exact search comes when a
        // budgeted one finds nothing again.
        approx_done = false;
        update(&mut st, round.plane, params, report)?;
    }
    report.planes = st.ws.planes.len();
    Ok(st.w)
}

/// Rounds over the cached locations only, each adding its plane while it
/// is violated by more than half of `epsilon` (at most `max_inner`).
fn cached_rounds(
    st: &mut State,
    layout: &Layout,
    examples: &mut [Example],
    params: &TrainParams,
    report: &mut TrainReport,
) -> Result<(), TrainError> {
    for _ in 0..params.solver.max_inner {
        let views = layout.to_views(&st.w);
        let det = Detector::new(&views)?;
        let t = Instant::now();
        let round = search::search(&det, layout, examples, params, false, None)?;
        report.cached_seconds += t.elapsed().as_secs_f64();
        let viol = st.violation(&round.plane);
        report.iterations += 1;
        if viol <= st.xi + params.solver.epsilon * 0.5 {
            break;
        }
        let t = Instant::now();
        update(st, round.plane, params, report)?;
        report.qp_seconds += t.elapsed().as_secs_f64();
    }
    Ok(())
}

/// The separation oracle at every location of every image (with a
/// budget of `mining_budget` locations per image unless `exact`): the
/// most violated output of each example, as one plane.
fn full_search(
    st: &State,
    layout: &Layout,
    examples: &mut [Example],
    params: &TrainParams,
    exact: bool,
    report: &mut TrainReport,
) -> Result<Round, TrainError> {
    let views = layout.to_views(&st.w);
    let det = Detector::new(&views)?;
    let t = Instant::now();
    let budget = (!exact).then_some(params.solver.mining_budget);
    let round = search::search(&det, layout, examples, params, true, budget)?;
    report.full_seconds += t.elapsed().as_secs_f64();
    if exact {
        report.exact_passes += 1;
    }
    report.full_min_cuts.push(round.min_cuts);
    report.full_violation.push(st.violation(&round.plane));
    report.passes += 1;
    Ok(round)
}

/// Whether a full search's violation is within `epsilon` of the slack.
fn converged(violation: f64, xi: f64, params: &TrainParams) -> bool {
    violation <= xi + params.solver.epsilon
}

/// Adds `plane` to the working set and solves the QP again.
fn update(
    st: &mut State,
    plane: Plane,
    params: &TrainParams,
    report: &mut TrainReport,
) -> Result<(), TrainError> {
    st.ws.add(plane);
    let sol = st.ws.solve(params.solver.c, &st.nonneg)?;
    st.w = sol.w;
    st.xi = sol.xi;
    report.objective.push(sol.objective);
    Ok(())
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}
