//! How busy the machine was while a benchmark ran, for the reports' headers.
//!
//! Wall-clock figures from a shared VM are only as good as the share of the CPUs the run got.
//! The load average does not show the main cause on this kind of machine: time the hypervisor
//! gives to other guests ("steal"), which a guest sees only in `/proc/stat`. Measured on the
//! 2-core VM these benches run on: 30-36 % steal at a load average of ~1.6, with the same
//! reconstruction taking 2.5-4x its time on a quiet machine. So every report states the steal
//! share over its run next to the load average.

use serde_json::{Value, json};

/// The aggregate CPU line of `/proc/stat`, in clock ticks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CpuTicks {
    /// user + nice + system + idle + iowait + irq + softirq + steal.
    pub total: u64,
    pub steal: u64,
    /// Time this guest's CPUs ran something: total - idle - iowait - steal.
    pub busy: u64,
}

impl CpuTicks {
    /// Parses the `cpu ` line of `/proc/stat` (fields: user nice system idle iowait irq softirq
    /// steal guest guest_nice; guest time is already counted in user). `None` if absent.
    pub fn parse(stat: &str) -> Option<CpuTicks> {
        let line = stat.lines().find(|l| l.starts_with("cpu "))?;
        let f: Vec<u64> = line
            .split_whitespace()
            .skip(1)
            .map(|v| v.parse().ok())
            .collect::<Option<_>>()?;
        if f.len() < 4 {
            return None;
        }
        let at = |i: usize| f.get(i).copied().unwrap_or(0);
        let total: u64 = (0..8).map(at).sum();
        Some(CpuTicks {
            total,
            steal: at(7),
            busy: total - at(3) - at(4) - at(7),
        })
    }

    /// Now, if `/proc/stat` is readable (Linux).
    pub fn now() -> Option<CpuTicks> {
        CpuTicks::parse(&std::fs::read_to_string("/proc/stat").ok()?)
    }
}

/// The machine's state at the start of a run; [`Contention::finish`] measures the run.
pub struct Contention {
    start: Option<CpuTicks>,
    load_at_start: String,
}

impl Contention {
    pub fn start() -> Self {
        Contention {
            start: CpuTicks::now(),
            load_at_start: load_average(),
        }
    }

    /// JSON for the report's `machine` object: load averages at both ends, and the shares of
    /// all CPU time over the run that was stolen (`steal_share`) and spent running this
    /// guest's work, any process (`busy_share`); both `null` without `/proc/stat`.
    pub fn finish(&self) -> Value {
        let shares = self
            .start
            .zip(CpuTicks::now())
            .and_then(|(a, b)| shares(a, b));
        json!({
            "load_average_at_start": self.load_at_start,
            "load_average_at_end": load_average(),
            "steal_share": shares.map(|s| s.0),
            "busy_share": shares.map(|s| s.1),
        })
    }
}

/// Adds [`Contention::finish`]'s fields to a report's `machine` object.
pub fn merge(machine: &mut Value, contention: &Value) {
    if let (Some(m), Some(c)) = (machine.as_object_mut(), contention.as_object()) {
        m.extend(c.iter().map(|(k, v)| (k.clone(), v.clone())));
    }
}

/// `(steal, busy)` as shares of the CPU ticks between `a` and `b`; `None` if none passed.
pub fn shares(a: CpuTicks, b: CpuTicks) -> Option<(f64, f64)> {
    let total = b.total.checked_sub(a.total)?;
    if total == 0 {
        return None;
    }
    let steal = b.steal.saturating_sub(a.steal) as f64 / total as f64;
    let busy = b.busy.saturating_sub(a.busy) as f64 / total as f64;
    Some((steal, busy))
}

/// One sentence for a report's header from [`Contention::finish`]'s JSON. Low steal does not
/// make a run quiet: other guests also compete for the host's caches and memory unseen (a
/// re-run of the targets at 1 % steal was 10-30 % slower than a run two hours earlier).
pub fn sentence(machine: &Value) -> String {
    let load = format!(
        "load average (1, 5, 15 min) {} at the start and {} at the end of the run",
        machine["load_average_at_start"].as_str().unwrap_or("?"),
        machine["load_average_at_end"].as_str().unwrap_or("?")
    );
    match machine["steal_share"].as_f64() {
        Some(s) => format!(
            "{load}; {:.0} % of the CPU time during the run was taken by the hypervisor for other guests (steal, from /proc/stat){}",
            100.0 * s,
            if s > 0.05 {
                ": the times are inflated by about that share or more"
            } else {
                ""
            }
        ),
        None => format!("{load}; steal time unknown (no /proc/stat)"),
    }
}

/// `/proc/loadavg` (1, 5 and 15 minute load averages), if readable.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_cpu_line_and_measures_shares() {
        let a = "cpu  100 5 50 800 10 1 4 30 0 0\ncpu0 50 2 25 400 5 0 2 15 0 0\nintr 1\n";
        let a = CpuTicks::parse(a).expect("parsed");
        assert_eq!(
            a,
            CpuTicks {
                total: 1000,
                steal: 30,
                busy: 160
            }
        );
        let b = CpuTicks::parse("cpu  200 5 60 900 10 1 4 130 0 0\n").expect("parsed");
        // 310 ticks passed: 100 stolen, 110 run (100 user, 10 system), 100 idle.
        let (steal, busy) = shares(a, b).expect("ticks passed");
        assert!((steal - 100.0 / 310.0).abs() < 1e-12);
        assert!((busy - 110.0 / 310.0).abs() < 1e-12);
        // Old kernels without the steal column, garbage, no time passed.
        let old = CpuTicks::parse("cpu 1 2 3 4\n").expect("four fields");
        assert_eq!((old.total, old.steal), (10, 0));
        assert_eq!(CpuTicks::parse("cpu x y\n"), None);
        assert_eq!(CpuTicks::parse("intr 5\n"), None);
        assert_eq!(shares(a, a), None);
    }

    #[test]
    fn the_sentence_warns_when_much_time_was_stolen() {
        let quiet = json!({"load_average_at_start": "0.1 0.1 0.1", "load_average_at_end": "1.0 0.5 0.2", "steal_share": 0.01});
        let busy = json!({"load_average_at_start": "1.6 1.6 1.7", "load_average_at_end": "2.0 1.7 1.7", "steal_share": 0.32});
        assert!(sentence(&quiet).contains("1 % of the CPU time"));
        assert!(!sentence(&quiet).contains("inflated"));
        assert!(sentence(&busy).contains("32 %") && sentence(&busy).contains("inflated"));
        assert!(sentence(&json!({})).contains("steal time unknown"));
    }
}
