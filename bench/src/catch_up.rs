//! What the floor's timer predicts for a chain's deadline misses once the chain's own cost is
//! added, catching up included.
//!
//! The floor is a bare timer: after a stall its one late wake-up covers every deadline that
//! passed, as a chain that cost nothing would. A real chain cannot: after a stall the plant
//! runs its late samples back to back, and each one costs the chain its CPU time per sample
//! (the stages' work and wake-ups, without the timer's wake-up), so it stays late for several
//! samples more and misses more deadlines than the floor (see docs/measurements.md, "Catching
//! up after a stall"). This model replays the floor's own wake-ups with a chain that
//! publishes its command `d` after the plant's wake-up and needs `c` per sample when it runs
//! samples back to back:
//!
//! out_j = max(wake_j + d, out_{j−1} + c), a miss when out_j > t_{j+1},
//!
//! where wake_j is the floor's wake-up that covered deadline t_j. With d = c = 0 it gives the
//! floor's own misses.

/// The floor's lateness at each deadline of one round (its wake-up that covered deadline j,
/// minus t_j), ns, saturated at `u32::MAX` (4.3 s).
pub type DeadlineLateness = Vec<u32>;

/// Misses of the modelled chain over one round of the floor (`late[j]`: the floor's lateness
/// at deadline j, ns) at sample time `ts_ns`, with the chain's command `d_ns` after the
/// plant's wake-up and `c_ns` of work per sample when samples run back to back.
pub fn misses(late: &[u32], ts_ns: u64, d_ns: u64, c_ns: u64) -> u64 {
    let ts = ts_ns as i64;
    let (d, c) = (d_ns as i64, c_ns as i64);
    // The previous command's time relative to its own deadline; far back before the first.
    let mut prev = i64::MIN / 2;
    let mut n = 0;
    for &l in late {
        let out = (l as i64 + d).max(prev - ts + c);
        n += u64::from(out > ts);
        prev = out;
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    const TS: u64 = 100_000;

    #[test]
    fn without_cost_the_model_is_the_floor() {
        // On time, 50 µs late, then a 350 µs stall that one wake-up covers (deadlines 3..6
        // all woken at t_3 + 350 µs: their lateness 350, 250, 150, 50 µs).
        let late = [
            10_000, 50_000, 20_000, 350_000, 250_000, 150_000, 50_000, 10_000,
        ];
        // The floor's rule: a deadline is missed when its wake-up is after the next deadline.
        let floor = late.iter().filter(|&&l| u64::from(l) > TS).count() as u64;
        assert_eq!(floor, 3);
        assert_eq!(misses(&late, TS, 0, 0), floor);
    }

    #[test]
    fn catching_up_costs_the_chain_more_deadlines_than_the_floor() {
        // A 350 µs stall at deadline 2, covered by one wake-up (lateness 350, 250, 150, 50 µs).
        let late = [
            10_000, 10_000, 350_000, 250_000, 150_000, 50_000, 10_000, 10_000, 10_000, 10_000,
        ];
        assert_eq!(misses(&late, TS, 0, 0), 3);
        // 10 µs behind the wake-up, 10 µs a sample when behind: commands at 360, 270, 180,
        // 90 µs after their deadlines: the same three misses.
        assert_eq!(misses(&late, TS, 10_000, 10_000), 3);
        // 60 µs a sample when behind: 360, 320, 280, 240, 200, 160, 120, then 80 µs (on
        // time): seven misses, as long as the lag takes to shrink below one period.
        assert_eq!(misses(&late, TS, 10_000, 60_000), 7);
    }

    #[test]
    fn a_median_offset_alone_misses_the_deadlines_it_pushes_past_the_period() {
        // Late 95 µs: on time for the floor, missed by a chain 10 µs behind its wake-up.
        let late = [95_000, 20_000];
        assert_eq!(misses(&late, TS, 0, 0), 0);
        assert_eq!(misses(&late, TS, 10_000, 0), 1);
    }
}
