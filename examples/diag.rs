use fleetslam_core::filter::FastSlam;
use fleetslam_core::log::record_order;
use fleetslam_data::run::add_header_robots;
use fleetslam_suite::experiments::{experiment_config, mrclam};
use std::path::PathBuf;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seed: u64 = args.first().map_or(3, |s| s.parse().unwrap());
    let particles: usize = args.get(1).map_or(1000, |s| s.parse().unwrap());
    let every: f64 = args.get(2).map_or(50.0, |s| s.parse().unwrap());
    let imp = mrclam(&PathBuf::from("../shared/datasets/mrclam-dataset6"), true, None, None);
    let mut cfg = experiment_config(&imp.log.header);
    cfg.particles = particles;
    cfg.seed = seed;
    let mut slam = FastSlam::new(cfg).unwrap();
    add_header_robots(&mut slam, &imp.log).unwrap();
    // group centres
    let mut groups: Vec<Vec<[f64; 2]>> = Vec::new();
    for l in &imp.truth.landmarks {
        let p = [l.mean[0], l.mean[1]];
        if let Some(g) = groups.iter_mut().find(|g| g.iter().any(|q| (q[0]-p[0]).hypot(q[1]-p[1]) < 0.3)) { g.push(p) } else { groups.push(vec![p]) }
    }
    let centres: Vec<[f64; 2]> = groups.iter().map(|g| { let n = g.len() as f64; [g.iter().map(|p| p[0]).sum::<f64>()/n, g.iter().map(|p| p[1]).sum::<f64>()/n] }).collect();
    let mut order: Vec<usize> = (0..imp.log.records.len()).collect();
    order.sort_by(|&a, &b| record_order(&imp.log.records[a], &imp.log.records[b]));
    let t_start = imp.log.records[order[0]].t;
    let mut next = t_start + every;
    for &i in &order {
        let rec = &imp.log.records[i];
        if slam.robot_index(&rec.robot).is_none() { continue; }
        slam.step(rec).unwrap();
        if rec.t >= next {
            next += every;
            let est = slam.estimate();
            let mut errs = String::new();
            for r in &est.robots {
                let tr = &imp.truth.trajectories[&r.id];
                let k = tr.partition_point(|p| p.t < r.last_t).min(tr.len()-1);
                let e = (tr[k].pose.x - r.mean.x).hypot(tr[k].pose.y - r.mean.y);
                errs += &format!(" {}:{:.2}", r.id, e);
            }
            let lms: Vec<[f64;2]> = est.landmarks.iter().map(|l| [l.gaussian.mean[0], l.gaussian.mean[1]]).collect();
            let mut gd = String::new();
            for c in &centres {
                let d = lms.iter().map(|l| (l[0]-c[0]).hypot(l[1]-c[1])).fold(f64::INFINITY, f64::min);
                gd += &format!(" {:.2}", d);
            }
            let spurious = lms.iter().filter(|l| centres.iter().all(|c| (l[0]-c[0]).hypot(l[1]-c[1]) > 0.3)).count();
            let all = slam.particles()[est.best_particle].map.len();
            println!("t={:6.0} ess={:6.1} err[{}] groups[{}] lms {} (all {}) spurious {}", rec.t - t_start, est.ess, errs, gd, lms.len(), all, spurious);
        }
    }
    println!("centres {:?}", centres);
    for l in slam.estimate().landmarks { println!("lm {:.2} {:.2} hits {} cov {:.3} {:.3}", l.gaussian.mean[0], l.gaussian.mean[1], l.hits, l.gaussian.cov[0], l.gaussian.cov[3]); }
}
