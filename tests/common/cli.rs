//! Running the binary as a user does, and reading what it wrote.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use translucent_tof::bag::BagReader;
use translucent_tof::msgs::Image;

/// Runs the binary with `dir` as its working directory.
pub fn run(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_translucent_tof"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("running the translucent_tof binary")
}

/// A run's exit status, standard output and standard error, for a failed assertion.
pub fn describe(out: &Output) -> String {
    format!(
        "status {:?}\n--- stdout ---\n{}\n--- stderr ---\n{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

pub fn assert_ok(out: &Output) {
    assert!(out.status.success(), "expected success, got {}", describe(out));
}

/// Every `sensor_msgs/Image` of a bag, by topic and stamp.
pub fn images(bag: &Path) -> BTreeMap<String, BTreeMap<u64, Image>> {
    let r = BagReader::open(bag).expect("reading a bag");
    let mut out: BTreeMap<String, BTreeMap<u64, Image>> = BTreeMap::new();
    for raw in r.messages() {
        let raw = raw.expect("a message");
        if raw.type_name == "sensor_msgs/msg/Image" {
            let img: Image = BagReader::decode(&raw).expect("an image");
            out.entry(raw.topic.to_string())
                .or_default()
                .insert(img.header.stamp.as_log_time_ns(), img);
        }
    }
    out
}
