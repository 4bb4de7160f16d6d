//! Push pacing of fragmented samples (patched in for translucent_tof issue 24;
//! see PATCHED.md at the crate root).
//!
//! A large sample is pushed as DATAFRAG datagrams of up to the path-MTU budget
//! (about 64 KiB on loopback). Sent back to back, they arrive at the remote
//! reader's socket faster than its receive thread is scheduled to drain them; a
//! reader on the OS-default receive buffer (Linux: 208 KiB, what Fast DDS uses
//! unless configured) then overflows after three or four of them, and every
//! sample loses a datagram: a best-effort reader loses the sample, a reliable
//! one must repair it. This token bucket, shared by all Writers of a
//! participant (they share the same remote sockets), spreads the DATAFRAG
//! datagrams of the push path: a burst of at most `burst` bytes, then
//! `rate` bytes per second.
//!
//! The rate follows the participant's push load, a running average of the
//! bytes of the user samples it starts to push per second:
//! `PUSH_PACING_LOAD_FACTOR` times that load, between
//! `PUSH_PACING_MIN_RATE_BYTES_PER_SEC` and `PUSH_PACING_RATE_BYTES_PER_SEC`,
//! with single-datagram bursts while the rate is below half the upper bound.
//! A light load (a 0.6 MB cloud at 10 Hz) thus leaves a remote reader time to
//! drain its socket between datagrams, and a heavy one (7.4 MB at 30 Hz) is not
//! held back below what it needs. The environment variables
//! `RUSTDDS_PUSH_BURST_BYTES` and `RUSTDDS_PUSH_RATE_BYTES_PER_SEC` fix the
//! burst and the rate instead.

use std::time::{Duration, Instant};

use crate::rtps::constant::{
  PUSH_PACING_BURST_BYTES, PUSH_PACING_LOAD_FACTOR, PUSH_PACING_LOAD_TAU_SECS,
  PUSH_PACING_MIN_RATE_BYTES_PER_SEC, PUSH_PACING_RATE_BYTES_PER_SEC,
  PUSH_PACING_SMALL_BURST_BYTES,
};

#[derive(Debug)]
pub(crate) struct PushPacer {
  burst: f64,
  rate: f64, // bytes per second
  tokens: f64,
  last: Instant,
  /// Running average of the bytes of user samples started per second.
  load: f64,
  /// Burst and rate fixed by the environment: no adaptation.
  fixed: bool,
}

impl PushPacer {
  pub(crate) fn new() -> Self {
    // Tuning overrides, read once per participant.
    let env = |name: &str| {
      std::env::var(name)
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&v| v > 0)
    };
    let (burst, rate) = (
      env("RUSTDDS_PUSH_BURST_BYTES"),
      env("RUSTDDS_PUSH_RATE_BYTES_PER_SEC"),
    );
    let fixed = burst.is_some() || rate.is_some();
    let mut p = Self {
      burst: burst.unwrap_or(PUSH_PACING_BURST_BYTES) as f64,
      rate: rate.unwrap_or(PUSH_PACING_RATE_BYTES_PER_SEC) as f64,
      tokens: 0.0,
      last: Instant::now(),
      load: 0.0,
      fixed,
    };
    p.adapt();
    p.tokens = p.burst;
    p
  }

  /// Rate and burst from the push load (unless fixed).
  fn adapt(&mut self) {
    if self.fixed {
      return;
    }
    let max = PUSH_PACING_RATE_BYTES_PER_SEC as f64;
    self.rate =
      (PUSH_PACING_LOAD_FACTOR * self.load).clamp(PUSH_PACING_MIN_RATE_BYTES_PER_SEC as f64, max);
    self.burst = if self.rate < 0.5 * max {
      PUSH_PACING_SMALL_BURST_BYTES as f64
    } else {
      PUSH_PACING_BURST_BYTES as f64
    };
    self.tokens = self.tokens.min(self.burst);
  }

  fn refill(&mut self) {
    let now = Instant::now();
    let dt = now.saturating_duration_since(self.last).as_secs_f64();
    self.last = now;
    self.tokens = (self.tokens + dt * self.rate).min(self.burst);
    self.load *= (-dt / PUSH_PACING_LOAD_TAU_SECS).exp();
  }

  /// May a datagram of `len` bytes go now? If not, the time to wait before
  /// asking again. A datagram larger than the burst goes when the bucket is
  /// full.
  pub(crate) fn wait_for(&mut self, len: usize) -> Option<Duration> {
    self.refill();
    let need = (len as f64).min(self.burst);
    if self.tokens >= need {
      None
    } else {
      Some(Duration::from_secs_f64((need - self.tokens) / self.rate))
    }
  }

  /// Counts `len` bytes sent. Every bulk (push) datagram of a user Writer is
  /// counted, also unfragmented ones, which are never held back: the bucket
  /// may go negative, and the next DATAFRAG waits longer.
  pub(crate) fn charge(&mut self, len: usize) {
    self.refill();
    self.tokens -= len as f64;
  }

  /// Counts a user sample of `len` bytes whose push starts now into the push
  /// load (when it starts, not as it goes out: a heavy load is seen before it
  /// has queued up behind a low rate).
  pub(crate) fn announce(&mut self, len: usize) {
    self.refill();
    self.load += len as f64 / PUSH_PACING_LOAD_TAU_SECS;
    self.adapt();
  }
}

#[cfg(test)]
mod tests {
  use super::*;

  #[test]
  fn burst_then_paced() {
    let mut p = PushPacer {
      burst: 100_000.0,
      rate: 1e6,
      tokens: 100_000.0,
      last: Instant::now(),
      load: 0.0,
      fixed: true,
    };
    assert_eq!(p.wait_for(60_000), None);
    p.charge(60_000);
    let wait = p.wait_for(60_000).unwrap();
    assert!(wait > Duration::from_millis(15) && wait <= Duration::from_millis(20));
    std::thread::sleep(wait);
    assert_eq!(p.wait_for(60_000), None);
    // An unfragmented datagram is counted although it was not held back.
    p.charge(200_000);
    assert!(p.wait_for(1).unwrap() > Duration::from_millis(100));
  }

  /// The participant's event loop waits for the bucket in `epoll_wait`, which
  /// rounds its timeout up to whole milliseconds, and a loaded machine wakes it
  /// later still; the tokens of a wait longer than `burst / rate` are lost. So
  /// the upper bound holds only with a burst of a few milliseconds at that
  /// rate: at 128 KiB and 256 MiB/s (0.5 ms) a loop waking every 2 ms would
  /// send a quarter of the rate.
  #[test]
  fn the_upper_bound_survives_late_wakeups() {
    let rate = PUSH_PACING_RATE_BYTES_PER_SEC as f64;
    for wake_ms in [1.0, 2.0, 3.0] {
      let mut p = PushPacer {
        burst: PUSH_PACING_BURST_BYTES as f64,
        rate,
        tokens: 0.0,
        last: Instant::now(),
        load: 0.0,
        fixed: true,
      };
      let (wakes, datagram) = (200, 65_000);
      let mut sent = 0usize;
      for _ in 0..wakes {
        // The loop sleeps `wake_ms`, then sends what the bucket allows.
        p.last -= Duration::from_secs_f64(wake_ms / 1e3);
        while p.wait_for(datagram).is_none() {
          p.charge(datagram);
          sent += datagram;
        }
      }
      let achieved = sent as f64 / (wakes as f64 * wake_ms / 1e3);
      assert!(
        achieved >= 0.95 * rate,
        "waking every {wake_ms} ms: {:.0} MiB/s of {:.0}",
        achieved / 1048576.0,
        rate / 1048576.0
      );
    }
  }

  #[test]
  fn the_rate_follows_the_load() {
    let mut p = PushPacer {
      burst: 0.0,
      rate: 0.0,
      tokens: 0.0,
      last: Instant::now(),
      load: 0.0,
      fixed: false,
    };
    p.adapt();
    // Idle: the lower bound, single datagrams.
    assert_eq!(p.rate, PUSH_PACING_MIN_RATE_BYTES_PER_SEC as f64);
    assert_eq!(p.burst, PUSH_PACING_SMALL_BURST_BYTES as f64);
    // 100 MB of samples within the time constant: the upper bound, larger bursts.
    for _ in 0..14 {
      p.announce(7_372_800);
    }
    assert_eq!(p.rate, PUSH_PACING_RATE_BYTES_PER_SEC as f64);
    assert_eq!(p.burst, PUSH_PACING_BURST_BYTES as f64);
  }
}
