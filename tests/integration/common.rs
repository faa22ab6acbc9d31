//! Helpers shared by the command-line integration tests: run the real `bgkmap` binary in a
//! temporary directory, check failures, write a simulated dataset, and read the few JSON / CSV
//! fields the tests need (no JSON crate: the outputs are flat objects).
#![allow(clippy::unwrap_used)]
#![allow(dead_code)] // builds with fewer features leave some helpers unused

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs `bgkmap ARGS…` with `dir` as the working directory (relative paths resolve there).
pub fn run<I, S>(dir: &Path, args: I) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    Command::new(env!("CARGO_BIN_EXE_bgkmap")).current_dir(dir).args(args).output().unwrap()
}

fn describe(args: &[String], out: &Output) -> String {
    format!(
        "bgkmap {}\nstatus: {}\n--- stdout ---\n{}\n--- stderr ---\n{}",
        args.join(" "),
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn strings<I, S>(args: I) -> Vec<String>
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    args.into_iter().map(|a| a.as_ref().to_string_lossy().into_owned()).collect()
}

/// Runs the binary, asserts success and returns its stdout.
pub fn run_ok<I, S>(dir: &Path, args: I) -> Vec<u8>
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let args = strings(args);
    let out = run(dir, &args);
    assert!(out.status.success(), "expected success:\n{}", describe(&args, &out));
    out.stdout
}

/// Like [`run_ok`], with stdout as UTF-8 text.
pub fn run_ok_text<I, S>(dir: &Path, args: I) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    String::from_utf8(run_ok(dir, args)).unwrap()
}

/// Runs the binary, asserts it fails (non-zero exit, `error: …` on stderr containing every
/// needle, case-insensitively) and returns stderr.
pub fn run_fail<I, S>(dir: &Path, args: I, needles: &[&str]) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let args = strings(args);
    let out = run(dir, &args);
    check_fail(&args, &out, needles)
}

/// Like [`run_fail`], and also checks the exit code (1: runtime error, 2: usage error).
pub fn run_fail_code<I, S>(dir: &Path, args: I, code: i32, needles: &[&str]) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let args = strings(args);
    let out = run(dir, &args);
    assert_eq!(out.status.code(), Some(code), "unexpected exit code:\n{}", describe(&args, &out));
    check_fail(&args, &out, needles)
}

fn check_fail(args: &[String], out: &Output, needles: &[&str]) -> String {
    let text = describe(args, out);
    assert!(!out.status.success(), "expected failure:\n{text}");
    assert!(out.status.code().is_some(), "killed by a signal:\n{text}");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(stderr.contains("error:"), "stderr lacks `error:`:\n{text}");
    let lower = stderr.to_lowercase();
    for n in needles {
        assert!(lower.contains(&n.to_lowercase()), "stderr lacks {n:?}:\n{text}");
    }
    stderr
}

/// Asserts that a failed command left nothing behind: `out` does not exist and `dir` holds no
/// temporary `*.tmp-*` sibling.
pub fn assert_no_output(dir: &Path, out: &str) {
    assert!(!dir.join(out).exists(), "{out} was created by a failing command");
    let stray: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp-"))
        .collect();
    assert!(stray.is_empty(), "stray temporary files: {stray:?}");
}

/// A simulated dataset written by `bgkmap simulate`.
#[derive(Debug)]
pub struct SimData {
    /// Scan file names relative to the working directory (`sim/scan_01.pcd`, …).
    pub scans: Vec<String>,
    /// `sim/truth.bt`.
    pub truth: String,
}

/// `bgkmap simulate --out sim --scans N` inside `dir`.
pub fn simulate(dir: &Path, scans: usize) -> SimData {
    run_ok(dir, ["simulate", "--out", "sim", "--scans", &scans.to_string()]);
    let scans: Vec<String> = (1..=scans).map(|i| format!("sim/scan_{i:02}.pcd")).collect();
    for s in &scans {
        assert!(dir.join(s).is_file(), "simulate did not write {s}");
    }
    let truth = "sim/truth.bt".to_string();
    assert!(dir.join(&truth).is_file(), "simulate did not write {truth}");
    SimData { scans, truth }
}

/// `bgkmap build --out OUT EXTRA… SCANS…`.
pub fn build(dir: &Path, out: &str, extra: &[&str], scans: &[String]) {
    let mut args: Vec<String> = vec!["build".into(), "--out".into(), out.into()];
    args.extend(extra.iter().map(|s| s.to_string()));
    args.extend(scans.iter().cloned());
    run_ok(dir, &args);
    assert!(dir.join(out).is_file(), "build did not write {out}");
}

/// `bgkmap export MAP --format csv` (to stdout).
pub fn export_csv(dir: &Path, map: &str) -> String {
    run_ok_text(dir, ["export", map, "--format", "csv"])
}

/// Where the sample data (la3dm's `sim_structured`) is looked for, beside the checkout.
pub const SAMPLE_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/la3dm/sim_structured");

/// The sample data directory. Tests that read it carry
/// `#[cfg_attr(not(bgkmap_sample_data), ignore = …)]` (build.rs sets the cfg when the data is
/// there), so they are reported as skipped without it. Only tests built with `cfg(bgkmap_sample_data)` run this, so
/// missing data here means it went away after the build: a failure, not a skip.
pub fn sample_dir() -> PathBuf {
    let d = PathBuf::from(SAMPLE_DIR);
    assert!(d.is_dir(), "{} not found (it was there when the tests were built)", d.display());
    d
}

/// The number after `"key":` in a flat JSON object.
pub fn json_number(json: &str, key: &str) -> f64 {
    let pat = format!("\"{key}\":");
    let start = json.find(&pat).unwrap_or_else(|| panic!("no key {key:?} in {json}")) + pat.len();
    let rest = json[start..].trim_start();
    let end = rest.find([',', '}', ']']).unwrap_or(rest.len());
    rest[..end]
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("{key}: {:?} is not a number ({e}) in {json}", &rest[..end]))
}

/// One CSV row of `export --format csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CsvRow {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub size: f64,
    pub probability: f64,
    pub variance: f64,
}

impl CsvRow {
    /// Integer cell key of the row's centre.
    pub fn key(&self) -> [i32; 3] {
        [self.x, self.y, self.z].map(|c| (c / self.size - 0.5).round() as i32)
    }
}

pub const CSV_HEADER: &str = "x,y,z,size,probability,variance";

/// Parses a whole CSV export (header checked), returning each row with its line.
pub fn parse_csv(csv: &str) -> Vec<(CsvRow, &str)> {
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some(CSV_HEADER));
    lines
        .map(|line| {
            let v: Vec<f64> = line
                .split(',')
                .map(|t| t.parse().unwrap_or_else(|_| panic!("bad CSV line {line:?}")))
                .collect();
            assert_eq!(v.len(), 6, "bad CSV line {line:?}");
            (CsvRow { x: v[0], y: v[1], z: v[2], size: v[3], probability: v[4], variance: v[5] }, line)
        })
        .collect()
}

/// A running `bgkmap serve` child process on loopback ports picked by the OS. Killed (SIGKILL)
/// when dropped unless [`ServeProcess::terminate`] ended it first.
#[derive(Debug)]
pub struct ServeProcess {
    child: Option<std::process::Child>,
    /// The bound gRPC address (from the `grpc listening on ADDR` line).
    pub grpc_addr: std::net::SocketAddr,
    /// The bound HTTP address (from the `http listening on ADDR` line).
    pub http_addr: std::net::SocketAddr,
    /// The zenoh locators (`zenoh listening on LOCATOR` lines, printed before gRPC's and HTTP's).
    pub zenoh_locators: Vec<String>,
    stderr: std::sync::Arc<std::sync::Mutex<String>>,
}

/// Starts `bgkmap serve --data-dir DATA_DIR --grpc-listen 127.0.0.1:0 --http-listen 127.0.0.1:0
/// EXTRA…` and waits (up to 60 s) until it prints both listening addresses.
pub fn start_serve(data_dir: &Path, extra: &[&str]) -> ServeProcess {
    start_serve_wrapped(data_dir, extra, &[])
}

/// As [`start_serve`], run through `wrapper` (a command that ends by exec'ing its arguments,
/// e.g. `["prlimit", "--fsize=1000000:unlimited", "--"]`), so the server keeps the child's pid.
pub fn start_serve_wrapped(data_dir: &Path, extra: &[&str], wrapper: &[&str]) -> ServeProcess {
    use std::io::{BufRead, Read};
    let bin = env!("CARGO_BIN_EXE_bgkmap");
    let mut cmd = match wrapper.split_first() {
        None => Command::new(bin),
        Some((program, args)) => {
            let mut c = Command::new(program);
            c.args(args).arg(bin);
            c
        }
    };
    let mut child = cmd
        .arg("serve")
        .arg("--data-dir")
        .arg(data_dir)
        .args(["--grpc-listen", "127.0.0.1:0", "--http-listen", "127.0.0.1:0"])
        .args(extra)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let mut err_pipe = child.stderr.take().unwrap();
    let sink = stderr.clone();
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = err_pipe.read(&mut buf) {
            if n == 0 {
                break;
            }
            sink.lock().unwrap().push_str(&String::from_utf8_lossy(&buf[..n]));
        }
    });
    let out = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        // Keeps reading to the end so the server never blocks on a full pipe.
        for line in std::io::BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            let _ = tx.send(line);
        }
    });
    let (mut grpc, mut http, mut zenoh_locators) = (None, None, Vec::new());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while grpc.is_none() || http.is_none() {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) => {
                if let Some(a) = line.strip_prefix("grpc listening on ") {
                    grpc = Some(a.trim().parse().unwrap());
                } else if let Some(a) = line.strip_prefix("http listening on ") {
                    http = Some(a.trim().parse().unwrap());
                } else if let Some(l) = line.strip_prefix("zenoh listening on ") {
                    zenoh_locators.push(l.trim().to_string());
                }
            }
            Err(_) => {
                let _ = child.kill();
                let status = child.wait().unwrap();
                panic!(
                    "bgkmap serve did not report its addresses ({status}); stderr:\n{}",
                    stderr.lock().unwrap()
                );
            }
        }
    }
    ServeProcess {
        child: Some(child),
        grpc_addr: grpc.unwrap(),
        http_addr: http.unwrap(),
        zenoh_locators,
        stderr,
    }
}

impl ServeProcess {
    /// `http://ADDR` of the gRPC port.
    pub fn grpc_url(&self) -> String {
        format!("http://{}", self.grpc_addr)
    }

    /// `http://ADDR` of the HTTP port.
    pub fn http_url(&self) -> String {
        format!("http://{}", self.http_addr)
    }

    /// What the server wrote to stderr so far.
    pub fn stderr(&self) -> String {
        self.stderr.lock().unwrap().clone()
    }

    /// The server's process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().unwrap().id()
    }

    /// Kills the server with SIGKILL (no draining, no flushing) and reaps it.
    pub fn kill(mut self) {
        let mut child = self.child.take().unwrap();
        child.kill().unwrap();
        child.wait().unwrap();
    }

    /// Sends SIGTERM and waits (up to 60 s) for the process to exit; returns its status.
    #[allow(unsafe_code)]
    pub fn terminate(mut self) -> std::process::ExitStatus {
        let mut child = self.child.take().unwrap();
        let pid = libc::pid_t::try_from(child.id()).unwrap();
        // SAFETY: plain kill(2) on our own child, which is not reaped yet (the pid is still ours).
        let sent = unsafe { libc::kill(pid, libc::SIGTERM) };
        assert_eq!(sent, 0, "kill(SIGTERM) failed: {}", std::io::Error::last_os_error());
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                return status;
            }
            if std::time::Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                panic!("bgkmap serve did not exit within 60 s of SIGTERM; stderr:\n{}", self.stderr());
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// One HTTP/1.1 request over a fresh connection (`Connection: close`); returns the status code
/// and the whole response text (headers and body).
pub fn http_request(addr: std::net::SocketAddr, method: &str, path: &str, body: &[u8]) -> (u16, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).unwrap();
    let _ = s.write_all(body);
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let text = String::from_utf8_lossy(&out).to_string();
    let code = text.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (code, text)
}
