//! Every test that opens a DDS participant runs in a private network
//! namespace with only loopback up, so that no discovery packet leaves the
//! machine. A test calls [`isolated`] first: outside a namespace it re-runs
//! itself inside a new one (`unshare --net`, loopback up with multicast) and
//! returns false; inside, it checks that loopback is the only interface and
//! returns true.

use std::process::Command;

const SETUP: &str = "ip link set lo up && ip link set lo multicast on && (ip route add 224.0.0.0/4 dev lo 2>/dev/null || true) && exec \"$@\"";

/// True when the caller runs inside a private namespace (run the test body);
/// false when the test has just run, and passed, in a child namespace.
pub fn isolated(test: &str) -> bool {
    if std::env::var("TTOF_NETNS").as_deref() == Ok("1") {
        // /proc/self/net follows the process's namespace (/sys would need a remount).
        let dev = std::fs::read_to_string("/proc/self/net/dev").expect("reading /proc/self/net/dev");
        let mut ifaces: Vec<String> = dev
            .lines()
            .skip(2)
            .filter_map(|l| l.split(':').next().map(|n| n.trim().to_string()))
            .collect();
        ifaces.sort();
        assert_eq!(
            ifaces,
            ["lo"],
            "a DDS test must run with loopback as the only interface"
        );
        return true;
    }
    let exe = std::env::current_exe().expect("test executable");
    let status = Command::new("unshare")
        .args(["--net", "--", "sh", "-c", SETUP, "sh"])
        .arg(&exe)
        // --include-ignored: the parent only gets here for a test it chose to run
        // (an ignored one only under --ignored), so the child must run it too.
        .args([test, "--exact", "--include-ignored", "--nocapture", "--test-threads=1"])
        .env("TTOF_NETNS", "1")
        .status()
        .unwrap_or_else(|e| panic!("running `unshare --net` for {test}: {e} (DDS tests need util-linux unshare and root or user namespaces)"));
    assert!(
        status.success(),
        "{test} failed inside its private network namespace ({status}); if unshare itself failed, DDS tests need root or unprivileged user namespaces"
    );
    false
}

/// Says that a test could not measure what it is for, where `scripts/test`'s
/// summary counts it (`N skipped`): written to the process's stderr itself, not
/// through the test harness's capture. `claim`: the test guards a README claim,
/// and `scripts/test` fails when it skips.
pub fn skipped(test: &str, claim: bool, why: &str) {
    use std::io::Write;
    let tag = if claim { "SKIPPED(claim)" } else { "SKIPPED" };
    // On a line of its own, in one write: inside `isolated`'s child (one test
    // thread) the harness has already printed `test NAME ... ` without a newline,
    // and `scripts/test` only counts the tag at the start of a line.
    let line = format!("\n{tag}: {test}: {why}\n");
    let _ = std::io::stderr().lock().write_all(line.as_bytes());
}
