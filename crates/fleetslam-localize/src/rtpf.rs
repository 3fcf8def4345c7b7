//! The mixture weights of the real-time particle filter (Kwok, Fox and Meila 2003/2004,
//! `shared/papers/real-time-particle-filters-kwok-fox-meila.txt`, section 3).
//!
//! When `k` observations arrive during one filter update (the window), RTPF spreads the
//! sample budget over them: sample set `i` integrates only observation `i`, and the belief at
//! the end of the window is the mixture `Bel_α = Σᵢ αᵢ Belᵢ` (paper eq. 3). The weights are
//! chosen to bring the mixture close to the belief `Bel*` that integrates all `k`
//! observations (eq. 2), by minimising the KL divergence (eq. 4-5)
//!
//! ```text
//! J(α) = KL(Bel_α ‖ Bel*) = ∫ Bel_α(x) log(Bel_α(x) / Bel*(x)) dx,   Σᵢ αᵢ = 1, αᵢ ≥ 0,
//! ∂J/∂αᵢ = ∫ Belᵢ(x) log(Bel_α(x) / Bel*(x)) dx + 1                          (eq. 6)
//! ```
//!
//! with a few steps of projected gradient descent from the centre `αᵢ = 1/k` (the constant
//! `+1` is the same for every `i` and vanishes on the simplex). The integrals are estimated by
//! Monte Carlo (section 3.3): trajectories are drawn from the previous belief and moved
//! through the window by the motion model alone (the proposal of eq. 7); importance weights
//! then give every belief from the same trajectories (`Belᵢ` ∝ `p(zᵢ | xᵢ)`, `Bel*` ∝
//! `Πⱼ p(zⱼ | xⱼ)`), so that all of them share the same random bits. Trajectories are
//! grouped by the connected regions of occupied cells of a grid over their end positions, and
//! the sums and normalisations of eq. 6 run over the groups, which lowers the variance of
//! the gradient and the bias from the different dynamics of the sample sets.

use fleetslam_core::math;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Parameters of the mixture-weight optimisation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RtpfParams {
    /// Gradient steps per window. Default 5 (the paper's "small number"). More steps move
    /// the weights further from uniform at the cost of following a noisier estimate.
    pub gradient_steps: usize,
    /// Step size of the projected gradient descent. Default 0.2. The gradient of a group is a
    /// log ratio of probabilities, of order 1 to 10; larger steps reach a vertex of the
    /// simplex (one observation only) in one step.
    pub step_size: f64,
    /// Trajectories for the gradient estimate; 0 picks `budget / (10 k)` (at least 20), so
    /// that evaluating `k` likelihoods per trajectory costs about a tenth of the update.
    pub trajectories: usize,
    /// Cell size of the grouping grid in x and y [m]. Default 0.5. Larger cells make fewer,
    /// larger groups: smoother and more biased gradients. A belief spread over the whole
    /// map with many trajectories fills the grid and makes one group (no gradient): keep
    /// the trajectories sparse.
    pub group_cell: f64,
    /// Cell size of the grouping grid in heading [rad]. Default 30° (0.5236).
    pub group_cell_theta: f64,
    /// Halve a gradient step until the criterion falls (Armijo's test). Default true: the
    /// criterion never rises. False takes every step at `step_size` whatever it does to
    /// the criterion (the behaviour before issue 17, kept for the ablation).
    pub backtracking: bool,
}

impl Default for RtpfParams {
    fn default() -> Self {
        Self {
            gradient_steps: 5,
            step_size: 0.2,
            trajectories: 0,
            group_cell: 0.5,
            group_cell_theta: 30f64.to_radians(),
            backtracking: true,
        }
    }
}

impl RtpfParams {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.step_size.is_finite() && self.step_size > 0.0) {
            return Err(format!(
                "rtpf.step_size must be a finite number > 0, got {}",
                self.step_size
            ));
        }
        if !(self.group_cell_theta.is_finite() && self.group_cell_theta > 0.0) {
            return Err(format!(
                "rtpf.group_cell_theta must be a finite angle > 0 [rad], got {}",
                self.group_cell_theta
            ));
        }
        if !(self.group_cell.is_finite() && self.group_cell > 0.0) {
            return Err(format!(
                "rtpf.group_cell must be a finite length > 0 [m], got {}",
                self.group_cell
            ));
        }
        if self.gradient_steps > 1000 {
            return Err(format!(
                "rtpf.gradient_steps must be at most 1000, got {}",
                self.gradient_steps
            ));
        }
        Ok(())
    }

    /// The number of trajectories for a window of `k` observations and a budget of `n`.
    pub fn trajectories_for(&self, n: usize, k: usize) -> usize {
        if self.trajectories > 0 {
            self.trajectories
        } else {
            (n / (10 * k.max(1))).max(20)
        }
    }
}

/// Groups poses by the connected regions of occupied cells of a grid over the state space
/// (x, y and heading; cells of `cell` metres and `cell_theta` radians, the heading axis
/// wrapping around), two cells being neighbours when they differ by at most one in every
/// axis. Returns the group of each pose, groups numbered from 0 in order of first
/// appearance.
pub fn group_by_grid(poses: &[[f64; 3]], cell: f64, cell_theta: f64) -> Vec<usize> {
    let nth = ((2.0 * std::f64::consts::PI / cell_theta).floor() as i64).max(1);
    let key = |p: &[f64; 3]| {
        (
            (p[0] / cell).floor() as i64,
            (p[1] / cell).floor() as i64,
            (((p[2] + std::f64::consts::PI) / cell_theta).floor() as i64).rem_euclid(nth),
        )
    };
    // Occupied cells in order of first appearance.
    let mut cells: HashMap<(i64, i64, i64), usize> = HashMap::new();
    let mut order: Vec<(i64, i64, i64)> = Vec::new();
    for p in poses {
        let c = key(p);
        if let std::collections::hash_map::Entry::Vacant(e) = cells.entry(c) {
            e.insert(order.len());
            order.push(c);
        }
    }
    // Union-find over cells.
    let mut parent: Vec<usize> = (0..order.len()).collect();
    fn find(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (i, &(cx, cy, ct)) in order.iter().enumerate() {
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dt in -1..=1 {
                    let n = (cx + dx, cy + dy, (ct + dt).rem_euclid(nth));
                    if let Some(&j) = cells.get(&n) {
                        let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                        if a != b {
                            parent[a.max(b)] = a.min(b);
                        }
                    }
                }
            }
        }
    }
    let mut label: HashMap<usize, usize> = HashMap::new();
    let mut cell_group = vec![0; order.len()];
    for (i, g) in cell_group.iter_mut().enumerate() {
        let root = find(&mut parent, i);
        let next = label.len();
        *g = *label.entry(root).or_insert(next);
    }
    poses.iter().map(|p| cell_group[cells[&key(p)]]).collect()
}

/// The per-group masses of the component beliefs and of the full belief.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupedBeliefs {
    /// `comp[i][g]`: the mass belief `i` (observation `i` only) puts on group `g`.
    pub comp: Vec<Vec<f64>>,
    /// `full[g]`: the mass of the belief with every observation.
    pub full: Vec<f64>,
}

/// Importance weights of the trajectories, summed per group (section 3.3).
///
/// `ll[i][m]` is the log-likelihood of observation `i` at trajectory `m`'s state at that
/// observation; `group[m]` the group of trajectory `m`. Component `i` weighs trajectory `m`
/// by `p(zᵢ | xᵢᵐ)`, the full belief by `Πᵢ p(zᵢ | xᵢᵐ)`; each is normalised over all
/// trajectories and summed per group.
pub fn grouped_beliefs(ll: &[Vec<f64>], group: &[usize]) -> GroupedBeliefs {
    let groups = group.iter().copied().max().map_or(0, |g| g + 1);
    let m = group.len();
    let normalised_sums = |logs: &[f64]| -> Vec<f64> {
        let max = logs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mut out = vec![0.0; groups];
        if !max.is_finite() {
            // Nothing explains the observation: every trajectory is as likely.
            for &g in group {
                out[g] += 1.0 / m as f64;
            }
            return out;
        }
        let w: Vec<f64> = logs.iter().map(|l| math::exp(l - max)).collect();
        let total: f64 = w.iter().sum();
        for (wm, &g) in w.iter().zip(group) {
            out[g] += wm / total;
        }
        out
    };
    let comp = ll.iter().map(|l| normalised_sums(l)).collect();
    let joint: Vec<f64> = (0..m).map(|t| ll.iter().map(|l| l[t]).sum()).collect();
    GroupedBeliefs {
        comp,
        full: normalised_sums(&joint),
    }
}

/// Probability floor inside the logarithms of the criterion, so that a group that one belief
/// misses gives a large but finite gradient.
const MASS_FLOOR: f64 = 1e-9;

/// The KL criterion `J(α) = Σ_g Bel_α(g) log(Bel_α(g) / Bel*(g))` over groups.
pub fn kl_criterion(b: &GroupedBeliefs, alpha: &[f64]) -> f64 {
    (0..b.full.len())
        .map(|g| {
            let mix: f64 = alpha.iter().zip(&b.comp).map(|(a, c)| a * c[g]).sum();
            if mix <= 0.0 {
                0.0
            } else {
                mix * math::ln((mix + MASS_FLOOR) / (b.full[g] + MASS_FLOOR))
            }
        })
        .sum()
}

/// The exact partial derivatives of [`kl_criterion`] (eq. 6 with the mass floor):
///
/// ```text
/// gᵢ = Σ_g Belᵢ(g) [ ln((Bel_α(g) + f) / (Bel*(g) + f)) + Bel_α(g) / (Bel_α(g) + f) ]
/// ```
///
/// With `f = 0` the bracket's second term is the `+1` of eq. 6: a constant that the
/// projection onto the simplex removes, so only the logarithm steers the weights.
pub fn kl_gradient(b: &GroupedBeliefs, alpha: &[f64]) -> Vec<f64> {
    let terms: Vec<f64> = (0..b.full.len())
        .map(|g| {
            let mix: f64 = alpha.iter().zip(&b.comp).map(|(a, c)| a * c[g]).sum();
            math::ln((mix + MASS_FLOOR) / (b.full[g] + MASS_FLOOR)) + mix / (mix + MASS_FLOOR)
        })
        .collect();
    b.comp
        .iter()
        .map(|c| c.iter().zip(&terms).map(|(m, l)| m * l).sum())
        .collect()
}

/// Euclidean projection onto the probability simplex (Duchi, Shalev-Shwartz, Singer and
/// Chandra 2008, fig. 1): sort, find the largest `ρ` with `u_ρ - (Σ_{j≤ρ} u_j - 1)/ρ > 0`,
/// subtract that threshold and clip at zero.
pub fn project_to_simplex(v: &[f64]) -> Vec<f64> {
    let n = v.len();
    if n == 0 {
        return Vec::new();
    }
    let mut u: Vec<f64> = v.to_vec();
    u.sort_by(|a, b| b.total_cmp(a));
    let mut cum = 0.0;
    let mut theta = 0.0;
    for (j, uj) in u.iter().enumerate() {
        cum += uj;
        let t = (cum - 1.0) / (j + 1) as f64;
        if uj - t > 0.0 {
            theta = t;
        }
    }
    let mut out: Vec<f64> = v.iter().map(|x| (x - theta).max(0.0)).collect();
    let s: f64 = out.iter().sum();
    if !(s > 0.0 && s.is_finite()) {
        return vec![1.0 / n as f64; n];
    }
    out.iter_mut().for_each(|x| *x /= s);
    out
}

/// Sufficient-decrease constant of the Armijo test: a step is accepted when the criterion
/// falls by at least this fraction of the decrease its linearisation predicts.
const ARMIJO: f64 = 1e-4;
/// Halvings of the step tried before a gradient step is given up (the weights are then at a
/// stationary point as far as the estimate can tell): `2^-30` of the step size.
const MAX_HALVINGS: usize = 30;

/// Mixture weights by projected gradient descent on the KL criterion, from `αᵢ = 1/k`
/// (paper section 3.2). Each of the `gradient_steps` steps starts at `step_size` and halves
/// it until the criterion falls enough (Armijo's test on the projected step), so that the
/// criterion never rises: a fixed step of the size that suits a flat criterion overshoots a
/// steep one to a vertex of the simplex.
pub fn optimise_weights(b: &GroupedBeliefs, params: &RtpfParams) -> Vec<f64> {
    let k = b.comp.len();
    let mut alpha = vec![1.0 / k as f64; k];
    let mut j = kl_criterion(b, &alpha);
    for _ in 0..params.gradient_steps {
        let g = kl_gradient(b, &alpha);
        let mut step = params.step_size;
        let mut accepted = false;
        for _ in 0..=MAX_HALVINGS {
            let stepped: Vec<f64> = alpha.iter().zip(&g).map(|(a, gi)| a - step * gi).collect();
            let cand = project_to_simplex(&stepped);
            if !params.backtracking {
                alpha = cand;
                accepted = true;
                break;
            }
            // The decrease the linearisation predicts, g·(α - α'), is >= 0 for a projection.
            let predicted: f64 = g
                .iter()
                .zip(alpha.iter().zip(&cand))
                .map(|(gi, (a, c))| gi * (a - c))
                .sum();
            if predicted <= 0.0 {
                break;
            }
            let jc = kl_criterion(b, &cand);
            if jc <= j - ARMIJO * predicted {
                alpha = cand;
                j = jc;
                accepted = true;
                break;
            }
            step *= 0.5;
        }
        if !accepted {
            break;
        }
        if !params.backtracking {
            j = kl_criterion(b, &alpha);
        }
    }
    alpha
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simplex_projection() {
        let p = project_to_simplex(&[0.5, 0.5, 0.5]);
        assert!(p.iter().all(|x| (x - 1.0 / 3.0).abs() < 1e-12));
        let p = project_to_simplex(&[2.0, 0.0, -1.0]);
        assert_eq!(p, vec![1.0, 0.0, 0.0]);
        let p = project_to_simplex(&[0.6, 0.5]);
        assert!((p[0] - 0.55).abs() < 1e-12 && (p[1] - 0.45).abs() < 1e-12);
    }

    #[test]
    fn grid_groups_are_connected_regions() {
        let pts = [
            [0.1, 0.1, 0.0],
            [1.2, 0.3, 0.1],
            [5.0, 5.0, 0.0],
            [0.5, 0.9, 0.0],
            [5.5, 6.5, 0.0],
            [9.0, 0.0, 0.0],
            // Same place, opposite heading: another group.
            [0.2, 0.2, 3.0],
            // Headings wrap: -3.1 and 3.1 are neighbours.
            [9.0, 0.1, -3.1],
            [9.0, 0.1, 3.1],
        ];
        let g = group_by_grid(&pts, 1.0, 0.5);
        assert_eq!(g, vec![0, 0, 1, 0, 1, 2, 3, 4, 4]);
    }

    /// A converged optimiser: many small steps (the default's 5 steps are for speed).
    fn converged() -> RtpfParams {
        RtpfParams {
            gradient_steps: 2000,
            step_size: 0.5,
            ..Default::default()
        }
    }

    /// The minimum of the criterion over a grid of the 3-simplex with `n` divisions.
    fn brute_force_3(b: &GroupedBeliefs, n: usize) -> (Vec<f64>, f64) {
        let mut best = (vec![], f64::INFINITY);
        for i in 0..=n {
            for j in 0..=(n - i) {
                let a = vec![
                    i as f64 / n as f64,
                    j as f64 / n as f64,
                    (n - i - j) as f64 / n as f64,
                ];
                let v = kl_criterion(b, &a);
                if v < best.1 {
                    best = (a, v);
                }
            }
        }
        best
    }

    fn normalised(v: Vec<f64>) -> Vec<f64> {
        let s: f64 = v.iter().sum();
        v.into_iter().map(|x| x / s).collect()
    }

    /// A 1D corridor of `CELLS` cells of 0.1 m with a uniform prior and three observations:
    /// two readings of the same place that disagree a little (likelihood peaks at 4.7 m and
    /// 5.2 m, of different widths, each with a weak echo at the symmetric place 10 m on),
    /// and an uninformative reading. The beliefs are exact per cell.
    const CELLS: usize = 200;
    fn likelihoods(x: f64) -> [f64; 3] {
        let g = |m: f64, s: f64| math::exp(-0.5 * ((x - m) / s).powi(2));
        [
            g(4.7, 0.6) + 0.05 * g(14.7, 0.6) + 1e-3,
            g(5.2, 0.4) + 0.05 * g(15.2, 0.4) + 1e-3,
            1.0,
        ]
    }
    fn exact_corridor() -> GroupedBeliefs {
        let xs: Vec<f64> = (0..CELLS).map(|c| (c as f64 + 0.5) * 0.1).collect();
        let comp = (0..3)
            .map(|i| normalised(xs.iter().map(|&x| likelihoods(x)[i]).collect()))
            .collect();
        let full = normalised(
            xs.iter()
                .map(|&x| likelihoods(x).iter().product())
                .collect(),
        );
        GroupedBeliefs { comp, full }
    }

    #[test]
    fn gradient_matches_central_finite_differences() {
        let b = GroupedBeliefs {
            comp: vec![
                vec![0.5, 0.2, 0.2, 0.1, 0.0],
                vec![0.1, 0.6, 0.1, 0.1, 0.1],
                vec![0.05, 0.05, 0.3, 0.3, 0.3],
            ],
            full: vec![0.3, 0.5, 0.1, 0.05, 0.05],
        };
        // Each partial derivative against its central finite difference, within `tol`.
        let check = |b: &GroupedBeliefs, alpha: &[f64], tol: f64, what: &str| {
            let h = 1e-6;
            let g = kl_gradient(b, alpha);
            for i in 0..alpha.len() {
                let (mut up, mut down) = (alpha.to_vec(), alpha.to_vec());
                up[i] += h;
                down[i] -= h;
                let fd = (kl_criterion(b, &up) - kl_criterion(b, &down)) / (2.0 * h);
                assert!(
                    (fd - g[i]).abs() < tol,
                    "{what} alpha {alpha:?} i {i}: fd {fd} grad {}",
                    g[i]
                );
            }
        };
        for alpha in [vec![0.2, 0.5, 0.3], vec![1.0 / 3.0; 3], vec![0.7, 0.1, 0.2]] {
            check(&b, &alpha, 1e-8, "table");
        }
        check(&exact_corridor(), &[0.25, 0.5, 0.25], 1e-7, "corridor");
    }

    #[test]
    fn a_full_belief_that_is_a_mixture_of_the_components_is_recovered() {
        // Bel* = 0.6 Bel₀ + 0.3 Bel₁ + 0.1 Bel₂ exactly: the optimum is those weights, J = 0.
        let comp = vec![
            vec![0.7, 0.2, 0.1, 0.0],
            vec![0.1, 0.1, 0.4, 0.4],
            vec![0.25, 0.25, 0.25, 0.25],
        ];
        let w = [0.6, 0.3, 0.1];
        let full = (0..4)
            .map(|g| (0..3).map(|i| w[i] * comp[i][g]).sum())
            .collect();
        let b = GroupedBeliefs { comp, full };
        assert!(kl_criterion(&b, &w).abs() < 1e-12);
        let (bf, jbf) = brute_force_3(&b, 100);
        assert!(
            bf.iter().zip(&w).all(|(a, b)| (a - b).abs() < 1e-9),
            "{bf:?}"
        );
        assert!(jbf.abs() < 1e-12);
        let a = optimise_weights(&b, &converged());
        assert!(a.iter().zip(&w).all(|(a, b)| (a - b).abs() < 2e-3), "{a:?}");
        // A full belief equal to one component: a vertex.
        let b1 = GroupedBeliefs {
            comp: b.comp.clone(),
            full: b.comp[1].clone(),
        };
        let a = optimise_weights(&b1, &converged());
        assert!(a[1] > 1.0 - 1e-7, "{a:?}");
    }

    #[test]
    fn optimiser_reaches_the_brute_force_optimum_of_an_exact_1d_problem() {
        let b = exact_corridor();
        let (bf, jbf) = brute_force_3(&b, 400);
        let a = optimise_weights(&b, &converged());
        let ja = kl_criterion(&b, &a);
        println!("brute force {bf:?} J {jbf}; optimiser {a:?} J {ja}");
        // The optimum is inside the simplex: mostly the sharper reading, a little of the
        // other (1.5 %), none of the flat one.
        assert!(bf[0] > 0.01 && bf[0] < 0.02 && bf[2] == 0.0, "{bf:?}");
        assert!(ja <= jbf + 1e-9, "optimiser J {ja} above the grid's {jbf}");
        assert!(
            a.iter().zip(&bf).all(|(x, y)| (x - y).abs() < 2.5e-3),
            "{a:?} vs {bf:?}"
        );
        // The default (5 steps) lowers the criterion from the uniform start, monotonically.
        let uniform = kl_criterion(&b, &[1.0 / 3.0; 3]);
        let mut last = uniform;
        for steps in 1..=5 {
            let p = RtpfParams {
                gradient_steps: steps,
                ..Default::default()
            };
            let j = kl_criterion(&b, &optimise_weights(&b, &p));
            assert!(j <= last, "step {steps}: {j} > {last}");
            last = j;
        }
        println!("uniform J {uniform}, default 5 steps J {last}, optimum {jbf}");
        assert!(last < uniform);
    }

    #[test]
    fn monte_carlo_beliefs_give_the_exact_problems_weights() {
        // Trajectories drawn from the prior and weighed per observation (section 3.3),
        // grouped by cell: the estimated weights approach the exact optimum.
        let exact = optimise_weights(&exact_corridor(), &converged());
        let m = 20_000;
        let mut rng = fleetslam_core::rng::stream(7, 0, 0);
        let xs: Vec<f64> = (0..m)
            .map(|_| rand::Rng::random::<f64>(&mut rng) * CELLS as f64 * 0.1)
            .collect();
        let ll: Vec<Vec<f64>> = (0..3)
            .map(|i| xs.iter().map(|&x| math::ln(likelihoods(x)[i])).collect())
            .collect();
        let group: Vec<usize> = xs
            .iter()
            .map(|x| ((x / 0.1) as usize).min(CELLS - 1))
            .collect();
        let est = optimise_weights(&grouped_beliefs(&ll, &group), &converged());
        println!("exact {exact:?} monte carlo {est:?}");
        assert!(
            est.iter().zip(&exact).all(|(a, b)| (a - b).abs() < 0.005),
            "{est:?} vs {exact:?}"
        );
    }

    #[test]
    fn gradient_descent_lowers_the_criterion_and_favours_the_informative_component() {
        // Three groups; component 0 is flat (an uninformative observation), component 1
        // agrees with the full belief.
        let b = GroupedBeliefs {
            comp: vec![vec![1.0 / 3.0; 3], vec![0.9, 0.05, 0.05]],
            full: vec![0.95, 0.025, 0.025],
        };
        let a0 = vec![0.5, 0.5];
        let a = optimise_weights(&b, &RtpfParams::default());
        assert!((a.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!(a[1] > 0.6, "{a:?}");
        assert!(kl_criterion(&b, &a) < kl_criterion(&b, &a0));
    }
}
