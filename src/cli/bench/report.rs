//! `bgkmap bench report`: every figure with a target, measured by the bench commands
//! themselves, run as a user runs them (child processes of this binary, one at a time), in
//! rounds: each round runs every bench once, so a host whose speed drifts weighs on every row
//! alike. The summary is the README's table: per figure the median of the rounds, their range,
//! how many rounds met the target, and a verdict from those counts.

use super::common::{bench_in_child, command_text};
use anyhow::{Context, Result};
use clap::Args;
use serde_json::{Value, json};
use std::ffi::OsString;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// PCD scans for the sample-scan rows (default: 12 scans of the built-in simulated room).
    pub scans: Vec<PathBuf>,
    /// Rounds, each running every bench once, in turn.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..))]
    pub rounds: u64,
    /// Small sizes throughout, to try the command: the figures are not comparable with the
    /// targets and get no verdict.
    #[arg(long)]
    pub quick: bool,
    /// Where `bench merge` and `bench restart` write their generated maps (removed after).
    #[arg(long, default_value = ".")]
    pub dir: PathBuf,
    /// Print one JSON object (every round's output of every bench, and the rows) instead of
    /// the table.
    #[arg(long)]
    pub json: bool,
    /// Also write that JSON object to this file (the table still goes to standard output).
    #[arg(long)]
    pub json_out: Option<PathBuf>,
}

/// What a figure must reach.
#[derive(Debug, Clone, Copy)]
enum Target {
    AtMost(f64),
    AtLeast(f64),
}

impl Target {
    fn met(self, x: f64) -> bool {
        match self {
            Target::AtMost(t) => x <= t,
            Target::AtLeast(t) => x >= t,
        }
    }

    fn text(self, unit: &str) -> String {
        match self {
            Target::AtMost(t) => format!("≤ {} {unit}", fmt(t)),
            Target::AtLeast(t) => format!("≥ {} {unit}", fmt(t)),
        }
    }
}

/// One row of the table: a figure read from one bench's JSON.
#[derive(Debug)]
struct Row {
    figure: &'static str,
    target: Option<Target>,
    unit: &'static str,
    /// The bench (see [`benches`]) whose output holds it.
    bench: &'static str,
    value: fn(&Value) -> Option<f64>,
}

fn at(v: &Value, pointer: &str) -> Option<f64> {
    v.pointer(pointer).and_then(Value::as_f64).filter(|x| x.is_finite())
}

fn rows() -> Vec<Row> {
    use Target::{AtLeast, AtMost};
    let row = |figure, target, unit, bench, value| Row { figure, target, unit, bench, value };
    let mut rows = vec![
        row(
            "sample scans, 1 thread, median per scan",
            Some(AtMost(0.5)),
            "ms",
            "sample",
            (|v| at(v, "/per_scan_ms_median")) as fn(&Value) -> Option<f64>,
        ),
        row("sample scans, 2 workers, rate over 1", Some(AtLeast(1.7)), "×", "sample_2w", |v| {
            at(v, "/speedup_vs_one_worker")
        }),
        row("dense 64-beam drive, 1 thread, median per scan", Some(AtMost(25.0)), "ms", "dense", |v| {
            at(v, "/per_scan_ms_median")
        }),
        // The target's parenthesis: ~130k raw points in 25 ms.
        row("dense drive, raw points/s of a median scan", Some(AtLeast(5.0)), "M/s", "dense", |v| {
            Some(at(v, "/raw_points")? / at(v, "/scans")? / at(v, "/per_scan_ms_median")? / 1e3)
        }),
        row("dense drive, raw points/s over whole passes", None, "M/s", "dense", |v| {
            Some(at(v, "/points_per_s")? / 1e6)
        }),
        row("dense drive, 2 workers, rate over 1", None, "×", "dense_2w", |v| {
            at(v, "/speedup_vs_one_worker")
        }),
    ];
    #[cfg(feature = "server")]
    rows.extend([
        row("points in-process, 100k per call, into a vector", Some(AtLeast(20.0)), "M/s", "query", |v| {
            Some(at(v, "/in_process/points_per_s")? / 1e6)
        }),
        row("points in-process, 100k per call, visited", Some(AtLeast(20.0)), "M/s", "query", |v| {
            Some(at(v, "/in_process/points_visited_per_s")? / 1e6)
        }),
        row("points over gRPC, 100k per call", Some(AtLeast(5.0)), "M/s", "query", |v| {
            Some(at(v, "/grpc/points_per_s")? / 1e6)
        }),
        row("points over zenoh, 100k per call", None, "M/s", "query", |v| {
            Some(at(v, "/zenoh/points_per_s")? / 1e6)
        }),
        row(
            "single point over gRPC, p99, while room scans stream in",
            Some(AtMost(1000.0)),
            "µs",
            "query",
            |v| at(v, "/grpc/single_p99_us_under_room_ingest"),
        ),
        row("room scans ingested meanwhile", None, "scans/s", "query", |v| {
            at(v, "/grpc/room_background_scans_per_s")
        }),
        row("8 m rays in-process", Some(AtLeast(1.0)), "M/s", "query", |v| {
            Some(at(v, "/in_process/rays_8m_per_s")? / 1e6)
        }),
        row("30 m rays in-process", None, "M/s", "query", |v| {
            Some(at(v, "/in_process/rays_30m_per_s")? / 1e6)
        }),
        row("1 m box in-process", None, "ms", "query", |v| at(v, "/in_process/box_1m_ms_median")),
        row("10 m box in-process", None, "ms", "query", |v| at(v, "/in_process/box_10m_ms_median")),
    ]);
    rows.extend([
        row("RAM per allocated cell, the larger of two maps", Some(AtMost(16.0)), "B", "scale", |v| {
            memory(v, "ram_bytes_per_allocated_cell")
        }),
        row("disk per allocated cell, the larger of two maps", Some(AtMost(4.0)), "B", "scale", |v| {
            memory(v, "disk_bytes_per_allocated_cell")
        }),
        row("ingest per scan, slowest / fastest map size", Some(AtMost(1.1)), "×", "scale", |v| {
            let ms: Vec<f64> = v["levels"]
                .as_array()?
                .iter()
                .map(|l| at(l, "/per_scan_ms_median"))
                .collect::<Option<_>>()?;
            let (lo, hi) = ms.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| (lo.min(x), hi.max(x)));
            (ms.len() >= 2 && lo > 0.0).then(|| hi / lo)
        }),
        row("exact merge of two large maps", None, "s", "merge", |v| at(v, "/merge_s")),
        row("restart: open a large map, replay its journal", None, "s", "restart", |v| at(v, "/open_s")),
    ]);
    rows
}

/// The larger of the outdoor and the room map's figure `key` (`bench scale`).
fn memory(v: &Value, key: &str) -> Option<f64> {
    let outdoor = at(v, &format!("/memory/outdoor/{key}"))?;
    Some(outdoor.max(at(v, &format!("/memory/room/{key}"))?))
}

fn os(args: &[&str]) -> Vec<OsString> {
    args.iter().map(OsString::from).collect()
}

/// The benches of a round, by name, with their arguments after `bgkmap`.
fn benches(a: &ReportArgs) -> Vec<(&'static str, Vec<OsString>)> {
    let q = a.quick;
    let pick = |quick: &'static str, full: &'static str| if q { quick } else { full };
    // `bench <name> --json`, and `quick` after it with `--quick`.
    let bench = |name: &str, quick: &[&str]| {
        let mut v = os(&["bench", name, "--json"]);
        if q {
            v.extend(os(quick));
        }
        v
    };
    let sample = |repeat: &str, threads: &str| {
        let mut v = os(&["bench", "ingest"]);
        v.extend(a.scans.iter().map(|p| p.clone().into_os_string()));
        v.extend(os(&["--repeat", repeat, "--threads", threads, "--json"]));
        v
    };
    let dense = |scans: &str, repeat: &str, threads: &str| {
        os(&["bench", "ingest", "--lidar64", scans, "--repeat", repeat, "--threads", threads, "--json"])
    };
    let large = |name: &str| {
        let mut v = bench(name, &["--blocks", "300", "--journal-scans", "5", "--points", "500"]);
        v.extend([OsString::from("--dir"), a.dir.clone().into_os_string()]);
        v
    };
    let mut list = vec![
        ("sample", sample(pick("3", "300"), "1")),
        ("sample_2w", sample(pick("4", "300"), "2")),
        ("dense", dense(pick("1", "6"), pick("1", "2"), "1")),
        ("dense_2w", dense(pick("2", "6"), pick("2", "4"), "2")),
    ];
    #[cfg(feature = "server")]
    list.push((
        "query",
        bench("query", &["--scans", "1", "--batch", "2000", "--latency-samples", "50", "--rays", "100"]),
    ));
    list.extend([
        ("scale", bench("scale", &["--levels", "0,1000", "--repeat", "1", "--outdoor-scans", "1"])),
        ("merge", large("merge")),
        ("restart", large("restart")),
    ]);
    list
}

pub fn run(a: ReportArgs) -> Result<()> {
    if a.scans.is_empty() && !a.quick {
        eprintln!("sample-scan rows: the built-in simulated room (give PCD files for la3dm's scans)");
    }
    if let Some(path) = &a.json_out {
        // Before the benches' minutes, not after them.
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?;
    }
    let benches = benches(&a);
    let mut runs: Vec<Vec<Value>> = benches.iter().map(|_| Vec::new()).collect();
    for round in 1..=a.rounds {
        for ((name, args), out) in benches.iter().zip(&mut runs) {
            eprintln!("round {round}/{}: bench {name}", a.rounds);
            out.push(bench_in_child(args).with_context(|| format!("bench {name}, round {round}"))?);
        }
    }
    let by_bench: serde_json::Map<String, Value> =
        benches.iter().zip(runs).map(|((n, _), v)| (n.to_string(), Value::Array(v))).collect();
    let summaries: Vec<Value> = rows()
        .iter()
        .map(|r| {
            let runs = by_bench.get(r.bench).and_then(Value::as_array).into_iter().flatten();
            let values: Vec<f64> = runs.filter_map(r.value).collect();
            summarise(r, &values, a.quick)
        })
        .collect();
    let machine = machine();
    let commands: Vec<String> = benches.iter().map(|(_, args)| command_text(args)).collect();
    let v = json!({
        "bench": "report",
        "rounds": a.rounds,
        "quick": a.quick,
        "machine": machine,
        "commands": commands,
        "rows": summaries,
        "runs": by_bench,
    });
    if let Some(path) = &a.json_out {
        std::fs::write(path, format!("{v}\n")).with_context(|| format!("cannot write {}", path.display()))?;
    }
    if a.json {
        println!("{v}");
        return Ok(());
    }
    println!("{}", table(&summaries, &machine, a.rounds, a.quick));
    println!("Each round ran, in turn:");
    for c in commands {
        println!("  {c}");
    }
    Ok(())
}

/// A row's figures over the rounds: median, range, rounds meeting the target, verdict.
fn summarise(r: &Row, values: &[f64], quick: bool) -> Value {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let median = match sorted.len() {
        0 => None,
        n if n % 2 == 1 => Some(sorted[n / 2]),
        n => Some((sorted[n / 2 - 1] + sorted[n / 2]) / 2.0),
    };
    let met = r.target.map(|t| values.iter().filter(|&&x| t.met(x)).count());
    let verdict = match (r.target, median, met) {
        _ if quick => "—".to_string(),
        (Some(t), Some(m), Some(k)) if k == values.len() && t.met(m) => "met in every round".into(),
        (Some(t), Some(m), Some(k)) if t.met(m) => {
            format!("met at the median ({k} of {} rounds)", values.len())
        }
        (Some(_), Some(_), Some(k)) => format!("not met ({k} of {} rounds)", values.len()),
        (Some(_), None, _) => "not measured".into(),
        _ => String::new(),
    };
    json!({
        "figure": r.figure,
        "target": r.target.map(|t| t.text(r.unit)),
        "unit": r.unit,
        "bench": r.bench,
        "values": values,
        "median": median,
        "min": sorted.first(),
        "max": sorted.last(),
        "rounds_met": met,
        "verdict": verdict,
    })
}

fn table(rows: &[Value], machine: &Value, rounds: u64, quick: bool) -> String {
    let mut s = format!(
        "bgkmap {} on {} ({} logical CPUs), {}: {rounds} round(s){}\n\n",
        env!("CARGO_PKG_VERSION"),
        machine["cpu"].as_str().unwrap_or("?"),
        machine["logical_cpus"],
        machine["date_utc"].as_str().unwrap_or("?"),
        if quick { ", quick sizes (no verdicts)" } else { "" },
    );
    s.push_str("| figure | target | median | range | verdict | bench |\n|---|---|---|---|---|---|\n");
    for r in rows {
        let num = |k: &str| r[k].as_f64().map(fmt).unwrap_or_else(|| "—".into());
        let unit = r["unit"].as_str().unwrap_or("");
        s.push_str(&format!(
            "| {} | {} | {} {unit} | {}–{} | {} | {} |\n",
            r["figure"].as_str().unwrap_or(""),
            r["target"].as_str().unwrap_or(""),
            num("median"),
            num("min"),
            num("max"),
            r["verdict"].as_str().unwrap_or(""),
            r["bench"].as_str().unwrap_or(""),
        ));
    }
    s
}

/// Three significant digits or so, never exponent notation.
fn fmt(x: f64) -> String {
    let decimals = match x.abs() {
        a if a >= 100.0 => 0,
        a if a >= 10.0 => 1,
        a if a >= 1.0 => 2,
        _ => 3,
    };
    format!("{x:.decimals$}")
}

/// The CPU model, logical CPUs and the time, for the table's heading.
fn machine() -> Value {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cpu = cpuinfo
        .lines()
        .find_map(|l| l.strip_prefix("model name").and_then(|r| r.split_once(':')).map(|(_, m)| m.trim()))
        .unwrap_or("unknown CPU");
    let secs =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    json!({
        "cpu": cpu,
        "logical_cpus": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        "date_utc": utc_text(secs),
    })
}

/// `YYYY-MM-DD HH:MM UTC` of a Unix time (the proleptic Gregorian calendar, by 400-year eras).
fn utc_text(secs: u64) -> String {
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    // Days since 0000-03-01, so a year's leap day is its last.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02} {:02}:{:02} UTC", rem / 3600, rem % 3600 / 60)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_text_known_days() {
        assert_eq!(utc_text(0), "1970-01-01 00:00 UTC");
        // 2000-02-29 12:34, a leap day of a century year divisible by 400.
        assert_eq!(utc_text(951_827_640), "2000-02-29 12:34 UTC");
        assert_eq!(utc_text(1_796_601_600), "2026-12-07 00:00 UTC");
        assert_eq!(utc_text(4_107_542_399), "2100-02-28 23:59 UTC");
    }

    #[test]
    fn verdicts_count_rounds() {
        let r =
            Row { figure: "f", target: Some(Target::AtMost(1.0)), unit: "ms", bench: "b", value: |_| None };
        let v = |xs: &[f64]| summarise(&r, xs, false)["verdict"].as_str().unwrap_or("").to_string();
        assert_eq!(v(&[0.5, 0.9, 1.0]), "met in every round");
        assert_eq!(v(&[0.5, 0.9, 1.2]), "met at the median (2 of 3 rounds)");
        assert_eq!(v(&[0.5, 1.1, 1.2]), "not met (1 of 3 rounds)");
        assert_eq!(v(&[]), "not measured");
        let s = summarise(&r, &[3.0, 1.0, 2.0, 10.0], false);
        assert_eq!(s["median"].as_f64(), Some(2.5));
        assert_eq!((s["min"].as_f64(), s["max"].as_f64()), (Some(1.0), Some(10.0)));
        assert_eq!(summarise(&r, &[0.5], true)["verdict"], "—");
    }
}
