//! One work item of a step: a contiguous run of particles taken through the record's
//! phases (poses and association, landmark updates, sightings, merging, existence).

use super::association::{associate_record, covering_radius};
use super::gauss::{compose_sandwich, sample_gaussian, upper3};
use super::proposal::{
    finish_proposal, propose, sample_motion, scaled_increment, sighting_marginal, sighting_update,
};
use super::proposal_lanes::{LaneProposal, propose_lanes};
use super::{Action, FilterStats, Particle, StepCtx};
use crate::config::{Association, FastSlamVersion};
use crate::ekf_lanes::LANES;
use crate::log::SensorRange;
use crate::map::Landmark;
use crate::map::{LandmarkMap, LandmarkMut};
use crate::math;
use crate::motion::{covariance_in_world_sc, scale_increment};
use crate::pose::{Pose2, PositionHeading, wrap_angle};
use crate::rng::Stream;
use crate::sensor::{LandmarkKind, MeasurementModel, Point3Model, RangeBearingModel};
use crate::stats::log_add_exp;
use crate::updater::{UpdateInput, UpdateNeeds, UpdateOutput};
use nalgebra::{Matrix2, Matrix3, SMatrix};
use std::f64::consts::PI;
use std::time::Instant;

/// What phase 1 decided for each particle of a work item, for the phases after it.
struct Decisions {
    /// Observations of the record.
    nobs: usize,
    /// `actions[i * nobs + j]`: what particle i does with observation j.
    actions: Vec<Action>,
    /// The Gaussian log-likelihood of the landmark explaining observation j best in
    /// particle i (same indexing), `-inf` if none.
    best_ll: Vec<f64>,
    /// Whether particle i weighs its observations from the updater's likelihoods (1.0, or a
    /// 2.0 particle whose proposal was degenerate) rather than from its proposal.
    weigh_in_update: Vec<bool>,
}

impl Decisions {
    fn action(&self, i: usize, j: usize) -> Action {
        self.actions[i * self.nobs + j]
    }

    fn best_ll(&self, i: usize, j: usize) -> f64 {
        self.best_ll[i * self.nobs + j]
    }
}

/// The particles of one work item, `base..base + particles.len()`, with the stepping
/// robot's entries of them (its pose, pose covariance and odometry scales in each).
pub(super) struct Chunk<'a> {
    pub(super) base: usize,
    pub(super) particles: &'a mut [Particle],
    pub(super) poses: &'a mut [Pose2],
    pub(super) pose_covs: &'a mut [[f64; 6]],
    pub(super) odometry_scales: &'a mut [[f64; 2]],
}

/// One work item: `chunk`'s particles, `headings` the robot's position and `(sin θ, cos θ)`
/// of its heading in each of them before the step, compiled for the instruction set `arch`
/// ([`ChunkWork`]).
pub(super) fn process_chunk(
    arch: pulp::Arch,
    ctx: &StepCtx<'_>,
    chunk: &mut Chunk<'_>,
    headings: &[PositionHeading],
) -> FilterStats {
    arch.dispatch(ChunkWork {
        ctx,
        chunk,
        headings,
    })
}

/// A work item as one [`pulp::WithSimd`] operation: `with_simd` and what it calls
/// `#[inline(always)]` (the phases, the proposal, the association, the sightings' marginal,
/// the random streams' set-up, the map's `update` and `for_each_near`) are compiled into
/// the function `Arch::dispatch` builds for the detected instruction set. What they do not
/// inline (the trie's write walk, `LandmarkMap::for_each`, `libm::atan`, the updater's batch
/// with its own dispatch) stays as it is. On the simulated speed log the dispatch took the
/// filter's steps from 3,741 M to 3,518 M instructions, and the inlining to 3,406 M
/// (README, session 28). The token `simd` lets 2D 2.0 proposals run four particles to a
/// vector ([`propose_lanes`]; README, session 29).
struct ChunkWork<'a, 'b, 'c> {
    ctx: &'a StepCtx<'b>,
    chunk: &'a mut Chunk<'c>,
    headings: &'a [PositionHeading],
}

impl pulp::WithSimd for ChunkWork<'_, '_, '_> {
    type Output = FilterStats;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> FilterStats {
        process_chunk_phases(simd, self.ctx, self.chunk, self.headings)
    }
}

/// The phases of a work item (inlined into [`ChunkWork::with_simd`]).
#[inline(always)]
fn process_chunk_phases<S: pulp::Simd>(
    simd: S,
    ctx: &StepCtx<'_>,
    chunk: &mut Chunk<'_>,
    headings: &[PositionHeading],
) -> FilterStats {
    let cfg = ctx.cfg;
    let mut stats = FilterStats::default();
    // A record without landmark observations reads no map (and every map already holds the
    // slots of the ids seen before it).
    if ctx.known_len > 0 && !ctx.obs.is_empty() {
        for p in chunk.particles.iter_mut() {
            p.map.ensure_slots(ctx.known_len);
        }
    }
    // 2.0 with deferred sampling: a record without landmark observations moves each
    // particle's pose Gaussian of this robot (its sightings update it) instead of sampling.
    let defer = ctx.defer;
    let decided = match cfg.landmark_kind {
        LandmarkKind::RangeBearing2d => {
            move_poses::<2, RangeBearingModel, S>(simd, ctx, chunk, headings, defer, &mut stats)
        }
        LandmarkKind::Point3d => {
            move_poses::<3, Point3Model, S>(simd, ctx, chunk, headings, defer, &mut stats)
        }
    };
    let observed = update_landmarks(ctx, chunk, &decided, &mut stats);
    if !ctx.sightings.is_empty() && !defer {
        weigh_sightings(ctx, chunk, &decided);
    }
    if let Some(observed) = &observed {
        merge_close_landmarks(ctx, chunk, observed, &mut stats);
        if !ctx.obs.is_empty() {
            lower_existence_in_view(ctx, chunk, observed, &mut stats);
        }
    }
    // Only observations and sightings change a weight.
    if !ctx.obs.is_empty() || !ctx.sightings.is_empty() {
        for p in chunk.particles.iter_mut() {
            if !p.log_w.is_finite() {
                p.log_w = f64::MIN;
            }
        }
    }
    stats
}

/// Particles between two stages of phase 1's prefetch of the record's landmarks: each
/// particle keeps its landmarks in trie nodes of its own, scattered over the heap, which
/// the loop would otherwise wait for one particle at a time, one level after the other. A
/// particle's landmark is asked for one trie level per stage, this many particles apart,
/// so that each level has arrived when the next stage reads it. (The robot's entries lie in
/// lists by robot, which the processor streams.)
const PREFETCH_AHEAD: usize = 4;

/// How many of the record's observations (the first ones with a known slot) have their
/// landmarks prefetched. Each costs a walk down the trie per stage and particle: MRCLAM's
/// records carry one or two, while for all 14 of the simulated speed log's the walks added
/// 11 % to the filter's instructions (callgrind, session 22) and no measured speed.
const PREFETCH_SLOTS: usize = 2;

/// The prefetch of phase 1 at particle `i` of `particles`: for each stage `k` of the trie
/// walk (`stages` of them), the particle `(stages - k) · PREFETCH_AHEAD` ahead has level `k`
/// of its paths to `slots` fetched (no effect on results).
#[inline(always)]
fn prefetch_landmarks(particles: &[Particle], i: usize, slots: &[usize], stages: u32) {
    for k in 0..stages {
        if let Some(p) = particles.get(i + (stages - k) as usize * PREFETCH_AHEAD) {
            for &slot in slots {
                p.map.prefetch_path(slot, k);
            }
        }
    }
}

/// The motion's prediction `N(mean0, pc0)` of the pose Gaussian `N(prev, prev_cov)` (a
/// point if `point`; `sc` its heading's sine and cosine) through the increment `inc`.
/// Inlined: returned through the stack from a call, its matrix was read back with wider loads
/// than it was written with, which stalled the loop (a store-forwarding failure).
#[inline(always)]
fn predict_motion(
    ctx: &StepCtx<'_>,
    prev: &Pose2,
    prev_cov: &[f64; 6],
    point: bool,
    sc: (f64, f64),
    inc: &Pose2,
) -> (Pose2, Matrix3<f64>) {
    let mut pc0 = covariance_in_world_sc(sc, &ctx.var);
    if !point {
        pc0 += compose_sandwich(sc, inc, prev_cov);
    }
    (prev.compose_sc(inc, sc), pc0)
}

/// Phase 1: each particle's new pose of the robot (deferred Gaussian, 2.0's proposal, or
/// 1.0's motion sample), the record's association, and in 2.0 the weights from the
/// proposal. Generic over the run's measurement model, which the caller picks.
#[inline(always)]
fn move_poses<const D: usize, M: MeasurementModel<D>, S: pulp::Simd>(
    simd: S,
    ctx: &StepCtx<'_>,
    c: &mut Chunk<'_>,
    headings: &[PositionHeading],
    defer: bool,
    stats: &mut FilterStats,
) -> Decisions {
    let cfg = ctx.cfg;
    let n = c.particles.len();
    let nobs = ctx.obs.len();
    // Each observation's measurement noise (it may grow with the measured range).
    let q: Vec<SMatrix<f64, D, D>> = ctx
        .obs
        .iter()
        .map(|o| M::noise(&cfg.sensor_noise, &o.z))
        .collect();
    let mut d = Decisions {
        nobs,
        actions: vec![Action::Ignore; n * nobs],
        best_ll: vec![f64::NEG_INFINITY; n * nobs],
        weigh_in_update: vec![true; n],
    };
    let slots: Vec<usize> = ctx
        .obs
        .iter()
        .filter_map(|o| o.slot)
        .take(PREFETCH_SLOTS)
        .collect();
    let stages = c.particles.first().map_or(0, |p| p.map.prefetch_stages());
    let shared = PhaseOne {
        ctx,
        q: &q,
        headings,
        slots: &slots,
        stages,
        defer,
    };
    // 2D 2.0 proposals of `LANES` particles at once where the instruction set has that
    // many f64 lanes ([`propose_lanes`]; the same bits as one by one).
    let lanes = cfg.version == FastSlamVersion::V2
        && nobs > 0
        && !defer
        && M::KIND == LandmarkKind::RangeBearing2d
        && S::F64_LANES == LANES;
    if !lanes {
        for i in 0..n {
            move_one::<D, M>(&shared, c, &mut d, stats, i);
        }
        return d;
    }
    let q2: Vec<Matrix2<f64>> = q
        .iter()
        .map(|m| m.fixed_view::<2, 2>(0, 0).into_owned())
        .collect();
    let blocks = n / LANES * LANES;
    for i in (0..blocks).step_by(LANES) {
        move_block::<D, M, S>(simd, &shared, &q2, c, &mut d, stats, i);
    }
    for i in blocks..n {
        move_one::<D, M>(&shared, c, &mut d, stats, i);
    }
    d
}

/// What phase 1's particles share.
struct PhaseOne<'a, 'b, const D: usize> {
    ctx: &'a StepCtx<'b>,
    /// Each observation's measurement noise.
    q: &'a [SMatrix<f64, D, D>],
    headings: &'a [PositionHeading],
    /// The prefetched slots and the trie walk's stages ([`prefetch_landmarks`]).
    slots: &'a [usize],
    stages: u32,
    /// 2.0's deferred sampling on this record.
    defer: bool,
}

/// Phase 1 for particle `i` of the work item.
#[inline(always)]
fn move_one<const D: usize, M: MeasurementModel<D>>(
    sh: &PhaseOne<'_, '_, D>,
    c: &mut Chunk<'_>,
    d: &mut Decisions,
    stats: &mut FilterStats,
    i: usize,
) {
    let PhaseOne {
        ctx,
        q,
        headings,
        slots,
        stages,
        defer,
    } = *sh;
    let nobs = d.nobs;
    let v2 = ctx.cfg.version == FastSlamVersion::V2;
    let calibrate = ctx.cfg.odometry_calibration.enabled();
    let (actions, best_ll, weigh_in_update) =
        (&mut d.actions, &mut d.best_ll, &mut d.weigh_in_update);
    if !slots.is_empty() {
        prefetch_landmarks(c.particles, i, slots, stages);
    }
    let p = &mut c.particles[i];
    let prev = c.poses[i];
    let prev_cov = c.pose_covs[i];
    // The particle's index in the filter, which keys its random stream of this step (32
    // bytes, a few dozen instructions to seed) and its entries in other robots' lists.
    let particle = c.base + i;
    let point = prev_cov.iter().all(|v| *v == 0.0);
    let sc = headings[i].sc();
    if defer {
        // Nothing is drawn (the scales' walk waits for a record that samples), so the
        // particle's stream is not set up. Most such records carry no sighting either:
        // the prediction stands, and the particle (its weight, its map) is not touched.
        let inc = if calibrate {
            scale_increment(&ctx.inc, c.odometry_scales[i])
        } else {
            ctx.inc
        };
        let (mean0, pc0) = predict_motion(ctx, &prev, &prev_cov, point, sc, &inc);
        if ctx.sightings.is_empty() {
            c.poses[i] = mean0;
            c.pose_covs[i] = upper3(&pc0);
        } else {
            let (pose, pc, dw) = sighting_update(ctx, particle, mean0, pc0);
            c.poses[i] = pose;
            c.pose_covs[i] = upper3(&pc);
            p.log_w += dw;
        }
        return;
    }
    let rng = &mut ctx.streams.lane(particle as u64);
    let inc = if calibrate {
        scaled_increment(ctx, &mut c.odometry_scales[i], rng)
    } else {
        ctx.inc
    };
    let (mean0, pc0) = predict_motion(ctx, &prev, &prev_cov, point, sc, &inc);
    let acts = &mut actions[i * nobs..(i + 1) * nobs];
    let bll = &mut best_ll[i * nobs..(i + 1) * nobs];
    c.pose_covs[i] = [0.0; 6];
    if v2 && nobs > 0 {
        associate_record::<D, M>(ctx, q, &p.map, &mean0, &pc0, acts, bll);
        if let Some((pose, dw)) =
            propose::<D, M>(ctx, q, &p.map, particle, &mean0, &pc0, acts, bll, rng)
        {
            c.poses[i] = pose;
            p.log_w += dw;
            weigh_in_update[i] = false;
            return;
        }
        stats.proposal_fallbacks += 1;
    }
    let pose = if point {
        sample_motion(ctx, &prev, &inc, rng)
    } else {
        sample_gaussian(&mean0, &pc0, rng)
    };
    c.poses[i] = pose;
    if nobs > 0 {
        associate_record::<D, M>(ctx, q, &p.map, &pose, &Matrix3::zeros(), acts, bll);
    }
}

/// Phase 1 for the [`LANES`] particles from `i` on, their 2.0 proposals (2D) in vectors of
/// `simd` ([`propose_lanes`]): each particle's motion and association first, then the
/// proposals together, then each particle's draw (or the scalar proposal for a lane that
/// left the vectors' common path, and 1.0's proposal for a degenerate one).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn move_block<const D: usize, M: MeasurementModel<D>, S: pulp::Simd>(
    simd: S,
    sh: &PhaseOne<'_, '_, D>,
    q2: &[Matrix2<f64>],
    c: &mut Chunk<'_>,
    d: &mut Decisions,
    stats: &mut FilterStats,
    i: usize,
) {
    let PhaseOne {
        ctx,
        q,
        headings,
        slots,
        stages,
        ..
    } = *sh;
    let nobs = d.nobs;
    let calibrate = ctx.cfg.odometry_calibration.enabled();
    let (actions, best_ll, weigh_in_update) =
        (&mut d.actions, &mut d.best_ll, &mut d.weigh_in_update);
    let mut rngs: [Stream; LANES] =
        std::array::from_fn(|l| ctx.streams.lane((c.base + i + l) as u64));
    let mut prior = [(Pose2::default(), Matrix3::zeros()); LANES];
    let mut incs = [Pose2::default(); LANES];
    let mut prevs = [Pose2::default(); LANES];
    let mut points = [false; LANES];
    for l in 0..LANES {
        let idx = i + l;
        if !slots.is_empty() {
            prefetch_landmarks(c.particles, idx, slots, stages);
        }
        let prev_cov = c.pose_covs[idx];
        prevs[l] = c.poses[idx];
        points[l] = prev_cov.iter().all(|v| *v == 0.0);
        let sc = headings[idx].sc();
        incs[l] = if calibrate {
            scaled_increment(ctx, &mut c.odometry_scales[idx], &mut rngs[l])
        } else {
            ctx.inc
        };
        prior[l] = predict_motion(ctx, &prevs[l], &prev_cov, points[l], sc, &incs[l]);
        c.pose_covs[idx] = [0.0; 6];
        let (mean0, pc0) = &prior[l];
        associate_record::<D, M>(
            ctx,
            q,
            &c.particles[idx].map,
            mean0,
            pc0,
            &mut actions[idx * nobs..(idx + 1) * nobs],
            &mut best_ll[idx * nobs..(idx + 1) * nobs],
        );
    }
    let mut acts = actions[i * nobs..(i + LANES) * nobs].chunks_mut(nobs);
    let mut acts: [&mut [Action]; LANES] =
        std::array::from_fn(|_| acts.next().expect("LANES particles' actions"));
    let bll: [&[f64]; LANES] =
        std::array::from_fn(|l| &best_ll[(i + l) * nobs..(i + l + 1) * nobs]);
    let maps: [&LandmarkMap; LANES] = std::array::from_fn(|l| &c.particles[i + l].map);
    let proposals = propose_lanes(simd, ctx, q2, maps, &prior, &mut acts, bll);
    for (l, proposal) in proposals.into_iter().enumerate() {
        let idx = i + l;
        let particle = c.base + idx;
        let (mean0, pc0) = &prior[l];
        let rng = &mut rngs[l];
        let acts = &mut actions[idx * nobs..(idx + 1) * nobs];
        let bll = &mut best_ll[idx * nobs..(idx + 1) * nobs];
        let map = &c.particles[idx].map;
        let proposed = match proposal {
            LaneProposal::Refined {
                mu,
                pc,
                dw,
                matched,
            } => finish_proposal(ctx, particle, mu, pc, dw, matched, rng),
            LaneProposal::Scalar => {
                associate_record::<D, M>(ctx, q, map, mean0, pc0, acts, bll);
                propose::<D, M>(ctx, q, map, particle, mean0, pc0, acts, bll, rng)
            }
        };
        if let Some((pose, dw)) = proposed {
            c.poses[idx] = pose;
            c.particles[idx].log_w += dw;
            weigh_in_update[idx] = false;
            continue;
        }
        stats.proposal_fallbacks += 1;
        let pose = if points[l] {
            sample_motion(ctx, &prevs[l], &incs[l], rng)
        } else {
            sample_gaussian(mean0, pc0, rng)
        };
        c.poses[idx] = pose;
        associate_record::<D, M>(ctx, q, map, &pose, &Matrix3::zeros(), acts, bll);
    }
}

/// Phase 2: the landmarks, one updater batch per observation (in calls of at most
/// `batch_size`), and in 1.0 the weights from the updates. Returns, with unknown
/// association and observations, the slots each particle observed (updated or created).
///
/// Each landmark to update is opened for writing once ([`LandmarkMap::get_mut`]): its prior
/// is read from the open cell and its posterior written into it after the batch, one trie
/// walk per update. The landmarks an observation creates are put into their maps after the
/// batch too (the open cells borrow the maps until then); a particle does one thing with
/// each observation, so the order of its map's and weight's changes is as it was.
#[inline(always)]
fn update_landmarks(
    ctx: &StepCtx<'_>,
    chunk: &mut Chunk<'_>,
    d: &Decisions,
    stats: &mut FilterStats,
) -> Option<Vec<Vec<usize>>> {
    if ctx.obs.is_empty() {
        return None;
    }
    let cfg = ctx.cfg;
    let n = chunk.particles.len();
    let outlier = cfg.association_params.outlier;
    let mut inputs: Vec<UpdateInput> = Vec::with_capacity(n);
    let mut outputs: Vec<UpdateOutput> = Vec::with_capacity(n);
    // The particles' new landmarks of an observation: (particle, slot if known, landmark).
    let mut created: Vec<(usize, Option<usize>, Landmark)> = Vec::new();
    // The open landmarks of an observation, reallocated per observation only in type (the
    // borrows end with each observation; `recycle` keeps the allocation).
    let mut open: Vec<Open<'_>> = Vec::with_capacity(n);
    let mut observed: Option<Vec<Vec<usize>>> =
        (cfg.association == Association::Unknown).then(|| vec![Vec::new(); n]);
    let a = &cfg.association_params;
    for (j, o) in ctx.obs.iter().enumerate() {
        inputs.clear();
        created.clear();
        let mut who = recycle(open);
        for (i, (p, &pose)) in chunk.particles.iter_mut().zip(&*chunk.poses).enumerate() {
            let mut action = d.action(i, j);
            let v1 = d.weigh_in_update[i];
            let mut weigh = v1;
            // A known id seen twice in one record: the second sighting updates the landmark
            // the first one created.
            if let Action::New(Some(s)) = action
                && p.map.get(s).is_some()
            {
                action = Action::Update(s);
                if !v1 {
                    // The proposal counted it as clutter; its likelihood comes from the update.
                    p.log_w -= o.clutter;
                    weigh = true;
                }
            }
            match action {
                Action::Update(s) => match p.map.get_mut(s) {
                    Some(lm) => {
                        inputs.push(UpdateInput {
                            prior: lm.get().gaussian,
                            pose,
                            z: o.z,
                        });
                        who.push(Open {
                            i,
                            s,
                            weigh,
                            lm,
                            log_w: &mut p.log_w,
                        });
                    }
                    // A known id the map does not hold yet is new (the association gives
                    // every id `Update` without looking it up; 2.0's proposal already made
                    // these `New`).
                    None => {
                        if v1 {
                            p.log_w += log_add_exp(d.best_ll(i, j), o.clutter);
                        }
                        created.push((i, Some(s), new_landmark(ctx, &pose, o)));
                    }
                },
                Action::New(slot) => {
                    if v1 {
                        p.log_w += log_add_exp(d.best_ll(i, j), o.clutter);
                    }
                    created.push((i, slot, new_landmark(ctx, &pose, o)));
                }
                Action::Ignore => {
                    if v1 {
                        p.log_w += log_add_exp(d.best_ll(i, j), o.clutter);
                    }
                    stats.ignored_observations += 1;
                }
                Action::Outlier => {
                    if v1 {
                        p.log_w += o.clutter;
                    }
                    stats.outliers += 1;
                }
            }
        }
        if !inputs.is_empty() {
            outputs.clear();
            outputs.resize(inputs.len(), UpdateOutput::default());
            // The likelihood only when a particle is weighed by it or the outlier gate reads
            // the Mahalanobis distance (FastSLAM 2.0 weighed the particles in its proposal).
            let needs = if outlier.is_some() || who.iter().any(|w| w.weigh) {
                UpdateNeeds::PosteriorAndLikelihood
            } else {
                UpdateNeeds::Posterior
            };
            let t0 = Instant::now();
            for (i, o) in inputs
                .chunks(cfg.batch_size)
                .zip(outputs.chunks_mut(cfg.batch_size))
            {
                ctx.updater.update_batch(needs, i, o);
            }
            stats.update_nanos += t0.elapsed().as_nanos() as u64;
            stats.landmark_updates += inputs.len() as u64;
        }
        for (w, out) in who.drain(..).zip(&outputs) {
            if w.weigh {
                let ll = if out.log_likelihood.is_finite() {
                    out.log_likelihood
                } else {
                    f64::NEG_INFINITY
                };
                *w.log_w += log_add_exp(ll, o.clutter);
            }
            if outlier.is_some_and(|b| out.mahalanobis2.is_nan() || out.mahalanobis2 > b) {
                stats.outliers += 1;
                continue;
            }
            if !out.posterior.is_finite() {
                continue;
            }
            w.lm.write(|lm| {
                lm.gaussian = out.posterior;
                lm.existence = (lm.existence + a.existence_hit).min(a.existence_max);
                lm.hits += 1;
            });
            if let Some(o) = &mut observed {
                o[w.i].push(w.s);
            }
        }
        open = recycle(who);
        for &(i, slot, lm) in &created {
            let map = &mut chunk.particles[i].map;
            let s = match slot {
                Some(s) => {
                    map.set(s, lm);
                    s
                }
                None => map.push(lm),
            };
            if let Some(o) = &mut observed {
                o[i].push(s);
            }
            stats.landmarks_created += 1;
        }
    }

    observed
}

/// A landmark opened for its update in phase 2: particle `i`'s landmark in slot `s`, its
/// cell, the particle's log-weight, and whether the update's likelihood weighs it.
struct Open<'a> {
    i: usize,
    s: usize,
    weigh: bool,
    lm: LandmarkMut<'a>,
    log_w: &'a mut f64,
}

/// An empty vector with `v`'s allocation for another lifetime of [`Open`] (the standard
/// library collects a vector's `into_iter` into its own allocation when the element
/// layouts agree).
#[inline(always)]
fn recycle<'b>(mut v: Vec<Open<'_>>) -> Vec<Open<'b>> {
    v.clear();
    v.into_iter()
        .map(|_| unreachable!("the vector was cleared"))
        .collect()
}

/// The landmark observation `o` creates, seen from `pose`.
#[inline(always)]
fn new_landmark(ctx: &StepCtx<'_>, pose: &Pose2, o: &super::Obs) -> Landmark {
    let a = &ctx.cfg.association_params;
    Landmark {
        gaussian: ctx.updater.initialize(pose, &o.z),
        id: o.id,
        existence: (a.existence_prior + a.existence_hit).min(a.existence_max),
        hits: 1,
    }
}

/// Phase 3: sightings of other robots weigh each particle by the same mixture, with the
/// sighting noise, marginal over the other robot's pose Gaussian (the deferred path and
/// 2.0's proposal with `sightings_in_proposal` weighed them already).
#[inline(always)]
fn weigh_sightings(ctx: &StepCtx<'_>, chunk: &mut Chunk<'_>, d: &Decisions) {
    let cfg = ctx.cfg;
    for (i, (p, pose)) in chunk.particles.iter_mut().zip(&*chunk.poses).enumerate() {
        if !d.weigh_in_update[i] && cfg.sightings_refine_proposal() {
            continue;
        }
        for s in ctx.sightings {
            let ll = sighting_marginal(
                ctx,
                chunk.base + i,
                s.robot,
                pose,
                &Matrix3::zeros(),
                &s.q,
                &s.z,
            )
            .map_or(f64::NEG_INFINITY, |m| m.0);
            p.log_w += log_add_exp(ll, s.clutter);
        }
    }
}

/// Phase 4 (unknown association): landmarks that this record brought closer than the
/// minimum separation to another landmark of their map are one landmark: the one observed
/// more often stays and takes the other's observation count and existence.
#[inline(always)]
fn merge_close_landmarks(
    ctx: &StepCtx<'_>,
    chunk: &mut Chunk<'_>,
    observed: &[Vec<usize>],
    stats: &mut FilterStats,
) {
    let a = &ctx.cfg.association_params;
    let sep2 = a.min_separation * a.min_separation;
    if sep2 <= 0.0 {
        return;
    }
    for (i, p) in chunk.particles.iter_mut().enumerate() {
        for &s in &observed[i] {
            let Some(l) = p.map.get(s).copied() else {
                continue;
            };
            // The landmark of lowest slot within the separation.
            let mut other: Option<(usize, Landmark)> = None;
            let (lx, ly) = (l.gaussian.mean[0], l.gaussian.mean[1]);
            p.map.for_each_near(lx, ly, covering_radius(sep2), |t, m| {
                if t != s
                    && (m.gaussian.mean[0] - lx).powi(2) + (m.gaussian.mean[1] - ly).powi(2) < sep2
                    && other.is_none_or(|(o, _)| t < o)
                {
                    other = Some((t, *m));
                }
            });
            let Some((t, m)) = other else {
                continue;
            };
            let (keep, kept, gone) =
                if (m.hits, std::cmp::Reverse(t)) > (l.hits, std::cmp::Reverse(s)) {
                    (t, m, l)
                } else {
                    (s, l, m)
                };
            let gone_slot = if keep == s { t } else { s };
            let existence = p
                .map
                .current_existence(keep, &kept)
                .max(p.map.current_existence(gone_slot, &gone));
            p.map.set(
                keep,
                Landmark {
                    hits: kept.hits + gone.hits,
                    existence,
                    ..kept
                },
            );
            p.map.remove(gone_slot);
            stats.landmarks_merged += 1;
        }
    }
}

/// Relative width of the band around the edges of the sensor's view (its range, and its
/// field as the cosine of the bearing) within which phase 5 decides whether a landmark is in
/// view by the definition (`hypot` of the offset, `atan2` of the bearing) rather than by
/// products (squared distance, the offset's dot product with the heading). The products'
/// rounding (about 1e-15 of the distance) and the definition's (`atan2` and the wrap within
/// an ulp of their results: about 3e-15 rad, plus an ulp of the heading) both lie far inside
/// it, so outside the band the two decide alike: a speed setting that changes no result
/// (the definition's `hypot` and `atan2` were 5 % of Victoria Park's instructions; README,
/// session 30).
const VIEW_EDGE_BAND: f64 = 1e-9;

/// The sensor's view from a heading, for phase 5: whether a landmark at offset `(dx, dy)`
/// from the robot lies within the range and the field of view.
#[derive(Debug, Clone, Copy)]
struct View {
    max_range: f64,
    r2: f64,
    /// Half the field of view, and its cosine.
    half: f64,
    cos_half: f64,
    theta: f64,
    sin: f64,
    cos: f64,
}

impl View {
    #[inline(always)]
    fn new(range: &SensorRange, theta: f64) -> Self {
        let half = 0.5 * range.fov;
        Self {
            max_range: range.max_range,
            r2: range.max_range * range.max_range,
            half,
            cos_half: math::cos(half),
            theta: 0.0,
            sin: 0.0,
            cos: 1.0,
        }
        .facing(theta)
    }

    /// The same view from heading `theta` (what depends on the range and the field is kept).
    #[inline(always)]
    fn facing(&self, theta: f64) -> Self {
        let (sin, cos) = math::sin_cos(theta);
        Self {
            theta,
            sin,
            cos,
            ..*self
        }
    }

    /// The definition: within the range (`hypot`) and the field of view (the bearing's
    /// `atan2`, wrapped, against half the field).
    fn contains_by_definition(&self, dx: f64, dy: f64) -> bool {
        math::hypot(dx, dy) < self.max_range
            && wrap_angle(math::atan2(dy, dx) - self.theta).abs() < self.half
    }

    /// The definition's decision by products, `None` within [`VIEW_EDGE_BAND`] of an edge of
    /// the view (or for a NaN); `d2` is `dx² + dy²`.
    #[inline(always)]
    fn by_products(&self, dx: f64, dy: f64, d2: f64) -> Option<bool> {
        if d2 > self.r2 * (1.0 + VIEW_EDGE_BAND) {
            return Some(false);
        }
        let clear_of_the_range = d2 < self.r2 * (1.0 - VIEW_EDGE_BAND);
        if !clear_of_the_range {
            return None;
        }
        if self.half > PI {
            // Every wrapped bearing lies within ±π.
            return Some(true);
        }
        // |bearing| < half ⟺ cos(bearing) > cos(half), for half in (0, π].
        let d = d2.sqrt();
        let margin = dx * self.cos + dy * self.sin - d * self.cos_half;
        if margin > VIEW_EDGE_BAND * d {
            Some(true)
        } else if margin < -VIEW_EDGE_BAND * d {
            Some(false)
        } else {
            None
        }
    }

    /// Whether the landmark is in view ([`View::contains_by_definition`], by products where
    /// they decide).
    #[inline(always)]
    fn contains(&self, dx: f64, dy: f64, d2: f64) -> bool {
        self.by_products(dx, dy, d2)
            .unwrap_or_else(|| self.contains_by_definition(dx, dy))
    }
}

/// Phase 5 (unknown association, with a sensor range): landmarks in the sensor's field of
/// view that the record did not observe lose existence log-odds, and are removed below
/// zero.
#[inline(always)]
fn lower_existence_in_view(
    ctx: &StepCtx<'_>,
    chunk: &mut Chunk<'_>,
    observed: &[Vec<usize>],
    stats: &mut FilterStats,
) {
    let a = &ctx.cfg.association_params;
    let Some(range) = &ctx.cfg.sensor_range else {
        return;
    };
    let reach = covering_radius(range.max_range * range.max_range);
    let sensor = View::new(range, 0.0);
    for (i, (p, &pose)) in chunk.particles.iter_mut().zip(&*chunk.poses).enumerate() {
        let seen = &observed[i];
        let mut missed: Vec<usize> = Vec::new();
        let view = sensor.facing(pose.theta);
        p.map.for_each_near(pose.x, pose.y, reach, |s, l| {
            let dx = l.gaussian.mean[0] - pose.x;
            let dy = l.gaussian.mean[1] - pose.y;
            // Beyond the covering radius it is out of range.
            let d2 = dx * dx + dy * dy;
            if d2 > reach * reach || seen.contains(&s) {
                return;
            }
            if view.contains(dx, dy, d2) {
                missed.push(s);
            }
        });
        for s in missed {
            let Some(e) = p.map.existence(s) else {
                continue;
            };
            let e = e - a.existence_miss;
            if e < 0.0 {
                p.map.remove(s);
                stats.landmarks_removed += 1;
            } else {
                // Held apart from the landmark: no leaf copy per landmark in view.
                p.map.set_existence(s, e);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn view(max_range: f64, fov: f64, theta: f64) -> View {
        View::new(&SensorRange { max_range, fov }, theta)
    }

    proptest! {
        /// Where the products decide, they decide as the definition does: landmarks
        /// anywhere, and on the view's edges (the range, the field's two sides) to within a
        /// few ulps, for fields from a sliver to all round and headings of any turn.
        #[test]
        fn the_view_by_products_is_the_definition(
            max_range in 0.5f64..100.0,
            fov in prop_oneof![0.01f64..6.2, Just(std::f64::consts::PI), Just(std::f64::consts::TAU), 6.3f64..7.0],
            theta in -20.0f64..20.0,
            edge in 0usize..4,
            u in -1.0f64..1.0,
            w in 0.0f64..1.2,
            ulps in -8i64..8,
        ) {
            let v = view(max_range, fov, theta);
            // A point at range `w · max_range` and bearing `u · half` off the heading; on the
            // range edge, or on one side of the field, moved by `ulps`.
            let nudge = |x: f64| f64::from_bits((x.to_bits() as i64 + ulps) as u64);
            let (r, b) = match edge {
                0 => (w * max_range, u * v.half),
                1 => (nudge(max_range), u * v.half),
                2 => (w * max_range, nudge(v.half)),
                _ => (w * max_range, -nudge(v.half)),
            };
            let (dx, dy) = (r * math::cos(theta + b), r * math::sin(theta + b));
            let d2 = dx * dx + dy * dy;
            if let Some(decided) = v.by_products(dx, dy, d2) {
                prop_assert_eq!(decided, v.contains_by_definition(dx, dy), "{} {}", dx, dy);
            }
            prop_assert_eq!(v.contains(dx, dy, d2), v.contains_by_definition(dx, dy));
        }
    }

    /// The products decide everything clear of the edges (so the definition's `hypot` and
    /// `atan2` are rare), and leave the edges to the definition.
    #[test]
    fn the_products_decide_away_from_the_edges() {
        let v = view(30.0, std::f64::consts::PI, 0.3);
        let at = |r: f64, b: f64| {
            let (dx, dy) = (r * math::cos(0.3 + b), r * math::sin(0.3 + b));
            v.by_products(dx, dy, dx * dx + dy * dy)
        };
        assert_eq!(at(10.0, 0.0), Some(true));
        assert_eq!(at(29.9, 1.5), Some(true));
        assert_eq!(at(30.1, 0.0), Some(false));
        assert_eq!(at(10.0, 1.6), Some(false));
        assert_eq!(at(10.0, -3.0), Some(false));
        assert_eq!(at(30.0, 0.0), None, "on the range's edge");
        assert_eq!(
            at(10.0, std::f64::consts::FRAC_PI_2),
            None,
            "on the field's edge"
        );
        assert_eq!(v.by_products(f64::NAN, 1.0, f64::NAN), None);
        assert_eq!(v.by_products(0.0, 0.0, 0.0), None, "on the robot");
        let round = view(30.0, 7.0, 0.3);
        assert_eq!(
            round.by_products(-10.0, 0.0, 100.0),
            Some(true),
            "all round"
        );
    }
}
