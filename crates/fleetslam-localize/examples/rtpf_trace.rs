//! One RTPF run of the paper-like building, window by window: which records saw a
//! distinguishing post, the mixture weights RTPF chose, and the belief's mass at the true
//! place after the update (`docs/rtpf.md`, "Why the weights miss").
//!
//! ```sh
//! cargo run --profile test --example rtpf_trace -- [SEED] [WINDOW] [SAMPLES] [WINDOWS_SHOWN]
//! ```
//!
//! Defaults: seed 0, window 10, 8000 samples, the first 14 windows.

use fleetslam_localize::config::Policy;
use fleetslam_localize::experiment::{RtpfExperiment, true_place_mass};
use fleetslam_localize::localizer::Localizer;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, default: u64| -> Result<u64, Box<dyn std::error::Error>> {
        Ok(match args.get(i) {
            Some(a) => a
                .parse()
                .map_err(|e| format!("argument {} ({a:?}): {e}", i + 1))?,
            None => default,
        })
    };
    let (seed, k, samples, shown) = (arg(0, 0)?, arg(1, 10)?, arg(2, 8000)?, arg(3, 14)?);
    let exp = RtpfExperiment {
        samples: samples as usize,
        ..RtpfExperiment::building()
    };
    exp.validate()?;
    let sim = exp.world.simulate(seed, exp.records, &exp.motion_noise);
    let cfg = exp.localize_config(Policy::Rtpf, k as usize);
    let mut loc = Localizer::new(exp.models(), cfg, seed.wrapping_mul(1000) + k)?;
    loc.initialise_with(exp.corridor_prior(seed), 0.0)?;
    println!("seed {seed}, window {k}, {samples} samples");
    println!("t [s] | records with a distinguishing post | weights | true-place mass");
    let mut start = 0;
    let mut windows = 0;
    for (i, r) in sim.records.iter().enumerate() {
        let Some(rep) = loc.push(r, &sim.map)? else {
            continue;
        };
        let (poses, w) = loc.posterior();
        let mass = true_place_mass(&poses, &w, &sim.truth[i]);
        let seen: Vec<String> = sim.features[start..=i]
            .iter()
            .map(|f| if *f > 0 { "x" } else { "." }.to_string())
            .collect();
        let alpha: Vec<String> = rep.alpha.iter().map(|a| format!("{a:.2}")).collect();
        println!(
            "{:5} | {} | {} | {mass:.3}",
            rep.t,
            seen.join(""),
            alpha.join(" ")
        );
        start = i + 1;
        windows += 1;
        if windows >= shown {
            break;
        }
    }
    Ok(())
}
