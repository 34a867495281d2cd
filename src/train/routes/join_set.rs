//! The join's choice for the set of shipped models (`sdhop-train join
//! --guard-scope set`): each object's setting chosen so that the models
//! together find the objects from any side best (the mean held-out figure
//! of the box folds), while the set's single-pose figures (the means over
//! objects of AUC, cross-object AUC, refined segmentation and VOC errors
//! on the guard's held-out photographs) stay no worse than those of the
//! set left unjoined. One object may give up a little single-pose accuracy
//! where another gains it, as the acceptance figures are the set's means;
//! `--guard-scope object` asks that of every object alone.
//!
//! Each object's figures depend on its own model only (its detections are
//! scored against every photograph), so the set's figures are sums over
//! objects and the choice is an exact search: branch and bound over each
//! object's candidates, the bounds being the best held-out figure and the
//! best single-pose figures the objects not yet chosen could add.
//!
//! With a time budget (`--max-time-ratio`, the default), each candidate
//! carries its measured time ([`super::join_cost`]) and the set's models
//! together may take at most the budget: the search then also prunes a
//! branch whose time, with the least the objects not yet chosen could
//! take, is over it.

use super::join::Candidate;

/// One option of an object in the search: its candidate (`None`: the
/// plain model), its held-out figure, its single-pose [`gains`] and its
/// time (0 without a budget).
type Opt = (Option<usize>, f64, [f64; 4], f64);

/// The four single-pose figures, oriented so that larger is better.
fn gains(s: &[f64; 4]) -> [f64; 4] {
    [s[0], s[1], -s[2], -s[3]]
}

/// Each object's index into its candidates (`None`: keep the base model),
/// maximising the set's held-out figure with the set's single-pose figures
/// within `tol` (per object, summed) of the unjoined set's and, with a
/// `budget`, the candidates' times (`cost_ms`, ms) summing to at most it.
/// A candidate other than the plain one must gain `min_gain` held out over
/// it, have a time where there is a budget and, joined, have components
/// to join; an object without plain single-pose figures keeps its base
/// model. Where no set fits the budget, every object keeps its base
/// model. Marks each candidate's `admissible`.
pub(super) fn pick_set(
    objects: &mut [(Vec<Candidate>, Option<usize>, bool)],
    tol: f64,
    min_gain: f64,
    budget: Option<f64>,
) -> Vec<Option<usize>> {
    let time = |c: &Candidate| match budget {
        Some(_) => c.cost_ms,
        None => Some(0.0),
    };
    // Per object: (candidate index or None for plain, held_out, gains).
    let mut opts: Vec<Vec<Opt>> = Vec::new();
    let mut floor = [0.0; 4];
    for (cs, plain, has_add) in objects.iter_mut() {
        let base = plain.and_then(|p| cs[p].single.map(|s| (cs[p].held_out, gains(&s))));
        let Some((held0, g0)) = base else {
            cs.iter_mut().for_each(|c| c.admissible = false);
            opts.push(vec![(None, 0.0, [0.0; 4], 0.0)]);
            continue;
        };
        let t0 = plain.and_then(|p| time(&cs[p])).unwrap_or(0.0);
        for (f, g) in floor.iter_mut().zip(g0) {
            *f += g - tol;
        }
        let mut o = vec![(None, held0, g0, t0)];
        for (i, c) in cs.iter_mut().enumerate() {
            c.admissible = Some(i) == *plain
                || (c.single.is_some()
                    && time(c).is_some()
                    && (c.setting.offset.is_none() || *has_add)
                    && c.held_out >= held0 + min_gain);
            if let (true, Some(s), Some(t), false) =
                (c.admissible, c.single, time(c), Some(i) == *plain)
            {
                o.push((Some(i), c.held_out, gains(&s), t));
            }
        }
        opts.push(pareto(o));
    }
    let n = opts.len();
    // Bounds of what objects k.. can add: best held-out, best per figure,
    // least time.
    let mut rest = vec![(0.0, [0.0; 4], 0.0); n + 1];
    for k in (0..n).rev() {
        let (h, g, t) = rest[k + 1];
        let best_h = opts[k]
            .iter()
            .map(|o| o.1)
            .fold(f64::NEG_INFINITY, f64::max);
        let mut best_g = [f64::NEG_INFINITY; 4];
        for o in &opts[k] {
            for (b, x) in best_g.iter_mut().zip(o.2) {
                *b = b.max(x);
            }
        }
        let least_t = opts[k].iter().map(|o| o.3).fold(f64::INFINITY, f64::min);
        rest[k] = (
            h + best_h,
            std::array::from_fn(|j| g[j] + best_g[j]),
            t + least_t,
        );
    }
    let mut search = Search {
        opts: &opts,
        rest: &rest,
        floor,
        budget: budget.unwrap_or(f64::INFINITY),
        path: vec![0; n],
        best: None,
    };
    search.dfs(0, 0.0, [0.0; 4], 0.0);
    let picks = search.best.map_or_else(|| vec![0; n], |(_, p)| p);
    picks.iter().zip(&opts).map(|(&i, o)| o[i].0).collect()
}

/// `o` without the options another is at least as good as in every
/// figure and as fast (the first of equals kept; the plain one first).
fn pareto(o: Vec<Opt>) -> Vec<Opt> {
    let at_least =
        |a: &Opt, b: &Opt| a.1 >= b.1 && a.3 <= b.3 && a.2.iter().zip(b.2).all(|(x, y)| *x >= y);
    let mut keep: Vec<Opt> = Vec::new();
    for (i, x) in o.iter().enumerate() {
        let dominated = o
            .iter()
            .enumerate()
            .any(|(j, y)| j != i && at_least(y, x) && (!at_least(x, y) || j < i));
        if !dominated {
            keep.push(*x);
        }
    }
    keep
}

struct Search<'a> {
    opts: &'a [Vec<Opt>],
    rest: &'a [(f64, [f64; 4], f64)],
    floor: [f64; 4],
    budget: f64,
    path: Vec<usize>,
    best: Option<(f64, Vec<usize>)>,
}

impl Search<'_> {
    fn dfs(&mut self, k: usize, held: f64, g: [f64; 4], t: f64) {
        let (h_rest, g_rest, t_rest) = self.rest[k];
        if t + t_rest > self.budget + 1e-9 {
            return;
        }
        if let Some((b, _)) = &self.best {
            if held + h_rest <= *b + 1e-12 {
                return;
            }
        }
        if (0..4).any(|j| g[j] + g_rest[j] < self.floor[j] - 1e-12) {
            return;
        }
        if k == self.opts.len() {
            self.best = Some((held, self.path.clone()));
            return;
        }
        for i in 0..self.opts[k].len() {
            let (_, h, x, dt) = self.opts[k][i];
            self.path[k] = i;
            self.dfs(
                k + 1,
                held + h,
                std::array::from_fn(|j| g[j] + x[j]),
                t + dt,
            );
        }
    }
}

/// Whether object `k` may move to `single` with the others as `chosen`
/// (each object's single-pose figures in the set) and `plain` (the
/// unjoined set's): the set's sums stay within `tol` per object.
pub(super) fn set_allows(
    chosen: &[Option<[f64; 4]>],
    plain: &[Option<[f64; 4]>],
    k: usize,
    single: [f64; 4],
    tol: f64,
) -> bool {
    let mut sum = [0.0; 4];
    let mut floor = [0.0; 4];
    for (i, (c, p)) in chosen.iter().zip(plain).enumerate() {
        let (Some(c), Some(p)) = (if i == k { Some(single) } else { *c }, p) else {
            continue;
        };
        let (gc, gp) = (gains(&c), gains(p));
        for j in 0..4 {
            sum[j] += gc[j];
            floor[j] += gp[j] - tol;
        }
    }
    (0..4).all(|j| sum[j] >= floor[j] - 1e-12)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::routes::join::Setting;

    fn cand(offset: Option<f64>, held_out: f64, single: [f64; 4]) -> Candidate {
        Candidate {
            setting: Setting {
                offset,
                colour_weight: 0.0,
                threshold: None,
            },
            folds: Vec::new(),
            held_out,
            single: Some(single),
            admissible: false,
            cost_ms: None,
        }
    }

    #[test]
    fn one_object_may_lose_what_another_gains() {
        // Object a: joining gains 0.3 from any side, loses 0.01 AUC.
        let a = vec![
            cand(None, 0.5, [0.98, 0.98, 0.25, 0.12]),
            cand(Some(0.5), 0.8, [0.97, 0.97, 0.25, 0.12]),
        ];
        // Object b: joining gains a little and 0.02 single-pose AUC.
        let b = vec![
            cand(None, 0.9, [0.95, 0.95, 0.25, 0.12]),
            cand(Some(0.0), 0.92, [0.97, 0.97, 0.25, 0.12]),
        ];
        let mut objects = vec![(a.clone(), Some(0), true), (b.clone(), Some(0), true)];
        let picks = pick_set(&mut objects, 0.0, 0.01, None);
        assert_eq!(picks, vec![Some(1), Some(1)]);
        // Alone, b cannot pay for a: a stays plain.
        let mut objects = vec![(a.clone(), Some(0), true), (b[..1].to_vec(), Some(0), true)];
        assert_eq!(pick_set(&mut objects, 0.0, 0.01, None), vec![None, None]);
        // With a tolerance that covers a's loss, a joins alone.
        let mut objects = vec![(a, Some(0), true), (b[..1].to_vec(), Some(0), true)];
        assert_eq!(
            pick_set(&mut objects, 0.006, 0.01, None),
            vec![Some(1), None]
        );
    }

    /// Three objects, four candidates each, random figures around the
    /// plain one's.
    fn random_objects(seed: u64) -> Vec<(Vec<Candidate>, Option<usize>, bool)> {
        let mut seed = seed;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as f64 / (1u64 << 31) as f64
        };
        (0..3)
            .map(|_| {
                let mut cs = vec![cand(None, 0.5, PLAIN)];
                for _ in 0..3 {
                    let s: [f64; 4] = std::array::from_fn(|j| PLAIN[j] + 0.02 * (next() - 0.35));
                    cs.push(cand(Some(0.0), 0.45 + 0.4 * next(), s));
                }
                (cs, Some(0), true)
            })
            .collect()
    }

    const PLAIN: [f64; 4] = [0.95, 0.95, 0.25, 0.12];

    /// The best feasible set by trying all 64.
    fn brute_force(objects: &[(Vec<Candidate>, Option<usize>, bool)]) -> Vec<usize> {
        let fig = |o: usize, i: usize| (objects[o].0[i].held_out, objects[o].0[i].single.unwrap());
        let mut best = (f64::NEG_INFINITY, vec![]);
        for i in 0..64 {
            let pick = [i % 4, (i / 4) % 4, i / 16];
            let sets: Vec<_> = (0..3).map(|o| fig(o, pick[o])).collect();
            // Below the least gain over the plain one: inadmissible.
            if sets.iter().zip(pick).any(|(x, c)| c > 0 && x.0 < 0.51) {
                continue;
            }
            let ok = (0..4).all(|q| {
                let s: f64 = sets.iter().map(|x| gains(&x.1)[q]).sum();
                s >= 3.0 * gains(&PLAIN)[q] - 1e-12
            });
            let h: f64 = sets.iter().map(|x| x.0).sum();
            if ok && h > best.0 + 1e-12 {
                best = (h, pick.to_vec());
            }
        }
        best.1
    }

    #[test]
    fn the_search_finds_the_best_feasible_set_among_all() {
        let mut joined = 0;
        for seed in 0..40 {
            let mut objects = random_objects(seed);
            let want = brute_force(&objects);
            let got: Vec<usize> = pick_set(&mut objects, 0.0, 0.01, None)
                .iter()
                .map(|p| p.unwrap_or(0))
                .collect();
            assert_eq!(got, want, "seed {seed}");
            joined += got.iter().filter(|&&i| i > 0).count();
        }
        // The draws are not all left plain.
        assert!(joined > 20, "{joined}");
    }

    #[test]
    fn the_search_keeps_the_sets_time_within_the_budget() {
        let mut tight = 0;
        for seed in 0..40 {
            let mut objects = random_objects(seed);
            // Each candidate's time: 10 ms plain, 10-30 joined.
            let mut draw = seed.wrapping_mul(2654435761) % 1000;
            for (cs, _, _) in objects.iter_mut() {
                for (i, c) in cs.iter_mut().enumerate() {
                    draw = (draw * 7919 + 13) % 1000;
                    c.cost_ms = Some(if i == 0 {
                        10.0
                    } else {
                        10.0 + draw as f64 / 50.0
                    });
                }
            }
            let budget = 45.0;
            let times: Vec<Vec<f64>> = objects
                .iter()
                .map(|(cs, _, _)| cs.iter().map(|c| c.cost_ms.unwrap()).collect())
                .collect();
            let time = |pick: &[usize]| -> f64 {
                pick.iter().enumerate().map(|(o, &i)| times[o][i]).sum()
            };
            // The best feasible set within the budget, by trying all 64.
            let figs = objects.clone();
            let fig = |o: usize, i: usize| (figs[o].0[i].held_out, figs[o].0[i].single.unwrap());
            let mut want = (f64::NEG_INFINITY, vec![0, 0, 0]);
            for i in 0..64 {
                let pick = [i % 4, (i / 4) % 4, i / 16];
                let sets: Vec<_> = (0..3).map(|o| fig(o, pick[o])).collect();
                if sets.iter().zip(pick).any(|(x, c)| c > 0 && x.0 < 0.51) || time(&pick) > budget {
                    continue;
                }
                let ok = (0..4).all(|q| {
                    let s: f64 = sets.iter().map(|x| gains(&x.1)[q]).sum();
                    s >= 3.0 * gains(&PLAIN)[q] - 1e-12
                });
                let h: f64 = sets.iter().map(|x| x.0).sum();
                if ok && h > want.0 + 1e-12 {
                    want = (h, pick.to_vec());
                }
            }
            let unbounded = pick_set(&mut objects.clone(), 0.0, 0.01, None);
            let got: Vec<usize> = pick_set(&mut objects, 0.0, 0.01, Some(budget))
                .iter()
                .map(|p| p.unwrap_or(0))
                .collect();
            assert_eq!(got, want.1, "seed {seed}");
            assert!(time(&got) <= budget, "seed {seed}");
            let free: Vec<usize> = unbounded.iter().map(|p| p.unwrap_or(0)).collect();
            if time(&free) > budget {
                tight += 1;
            }
        }
        // The budget binds in some draws.
        assert!(tight > 5, "{tight}");
        // A candidate without a time cannot be chosen under a budget.
        let mut objects = random_objects(3);
        let picks = pick_set(&mut objects, 0.0, 0.01, Some(1e9));
        assert_eq!(picks, vec![None, None, None]);
    }

    #[test]
    fn the_set_allows_a_move_only_within_the_unjoined_sets_figures() {
        let plain = vec![Some([0.9, 0.9, 0.2, 0.1]), Some([0.9, 0.9, 0.2, 0.1])];
        let chosen = vec![Some([0.92, 0.92, 0.19, 0.09]), Some([0.9, 0.9, 0.2, 0.1])];
        assert!(set_allows(
            &chosen,
            &plain,
            1,
            [0.89, 0.89, 0.21, 0.11],
            0.0
        ));
        assert!(!set_allows(&chosen, &plain, 1, [0.87, 0.9, 0.2, 0.1], 0.0));
        assert!(set_allows(&chosen, &plain, 1, [0.87, 0.9, 0.2, 0.1], 0.005));
    }
}
