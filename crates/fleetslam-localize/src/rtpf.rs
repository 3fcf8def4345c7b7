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
}

impl Default for RtpfParams {
    fn default() -> Self {
        Self {
            gradient_steps: 5,
            step_size: 0.2,
            trajectories: 0,
            group_cell: 0.5,
            group_cell_theta: 30f64.to_radians(),
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
        let w: Vec<f64> = logs.iter().map(|l| (l - max).exp()).collect();
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
                mix * ((mix + MASS_FLOOR) / (b.full[g] + MASS_FLOOR)).ln()
            }
        })
        .sum()
}

/// The gradient of eq. 6 without the constant: `gᵢ = Σ_g Belᵢ(g) log(Bel_α(g) / Bel*(g))`.
pub fn kl_gradient(b: &GroupedBeliefs, alpha: &[f64]) -> Vec<f64> {
    let logs: Vec<f64> = (0..b.full.len())
        .map(|g| {
            let mix: f64 = alpha.iter().zip(&b.comp).map(|(a, c)| a * c[g]).sum();
            ((mix + MASS_FLOOR) / (b.full[g] + MASS_FLOOR)).ln()
        })
        .collect();
    b.comp
        .iter()
        .map(|c| c.iter().zip(&logs).map(|(m, l)| m * l).sum())
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

/// Mixture weights by projected gradient descent on the KL criterion, from `αᵢ = 1/k`.
pub fn optimise_weights(b: &GroupedBeliefs, params: &RtpfParams) -> Vec<f64> {
    let k = b.comp.len();
    let mut alpha = vec![1.0 / k as f64; k];
    for _ in 0..params.gradient_steps {
        let g = kl_gradient(b, &alpha);
        let stepped: Vec<f64> = alpha
            .iter()
            .zip(&g)
            .map(|(a, gi)| a - params.step_size * gi)
            .collect();
        alpha = project_to_simplex(&stepped);
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
