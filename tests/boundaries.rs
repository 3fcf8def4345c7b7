//! The algorithm crate stays free of async runtimes, web frameworks, databases and burn.

use std::process::Command;

#[test]
fn core_has_no_runtime_web_database_or_burn_dependency() {
    check_crate("fleetslam-core");
}

#[test]
fn localize_has_no_runtime_web_database_or_burn_dependency() {
    check_crate("fleetslam-localize");
}

fn check_crate(krate: &str) {
    let out = Command::new(env!("CARGO"))
        .args([
            "tree",
            "-p",
            krate,
            "-e",
            "normal,build",
            "--prefix",
            "none",
            "--format",
            "{p}",
            "--offline",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("running cargo tree");
    assert!(
        out.status.success(),
        "cargo tree failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tree = String::from_utf8_lossy(&out.stdout);
    let names: Vec<&str> = tree
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    assert!(names.contains(&"nalgebra"), "unexpected tree:\n{tree}");
    for banned in [
        "tokio",
        "axum",
        "hyper",
        "sqlx",
        "burn",
        "burn-core",
        "async-std",
    ] {
        assert!(
            !names.contains(&banned),
            "{krate} must not depend on {banned}:\n{tree}"
        );
    }
}

/// The learned updater's inference path (default features: what the server links) builds
/// without burn; only its `train` feature brings burn in.
#[test]
fn learned_updater_without_train_feature_has_no_burn() {
    let tree = |features: &[&str]| -> Vec<String> {
        let mut args = vec![
            "tree",
            "-p",
            "fleetslam-learned",
            "-e",
            "normal,build",
            "--prefix",
            "none",
            "--format",
            "{p}",
            "--offline",
        ];
        args.extend_from_slice(features);
        let out = Command::new(env!("CARGO"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .output()
            .expect("running cargo tree");
        assert!(
            out.status.success(),
            "cargo tree failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|l| l.split_whitespace().next().map(str::to_string))
            .collect()
    };
    let plain = tree(&[]);
    assert!(plain.iter().any(|n| n == "fleetslam-core"), "{plain:?}");
    assert!(
        !plain.iter().any(|n| n.starts_with("burn")),
        "fleetslam-learned without `train` must not depend on burn: {plain:?}"
    );
    let with_train = tree(&["--features", "train"]);
    assert!(with_train.iter().any(|n| n == "burn"), "{with_train:?}");
}
