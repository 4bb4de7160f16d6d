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

use std::time::{Duration, Instant};

use crate::rtps::constant::{PUSH_PACING_BURST_BYTES, PUSH_PACING_RATE_BYTES_PER_SEC};

#[derive(Debug)]
pub(crate) struct PushPacer {
  burst: f64,
  rate: f64, // bytes per second
  tokens: f64,
  last: Instant,
}

impl PushPacer {
  pub(crate) fn new() -> Self {
    // Tuning overrides, read once per participant.
    let env = |name: &str, default: usize| {
      std::env::var(name)
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&v| v > 0)
        .unwrap_or(default)
    };
    let burst = env("RUSTDDS_PUSH_BURST_BYTES", PUSH_PACING_BURST_BYTES) as f64;
    let rate = env(
      "RUSTDDS_PUSH_RATE_BYTES_PER_SEC",
      PUSH_PACING_RATE_BYTES_PER_SEC,
    ) as f64;
    Self {
      burst,
      rate,
      tokens: burst,
      last: Instant::now(),
    }
  }

  fn refill(&mut self) {
    let now = Instant::now();
    let dt = now.saturating_duration_since(self.last).as_secs_f64();
    self.last = now;
    self.tokens = (self.tokens + dt * self.rate).min(self.burst);
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
}
