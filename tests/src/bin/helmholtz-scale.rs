//! Scale benchmark (on demand, not a test): one camera session's transport matrix (T) solved by
//! 1, 2, 4 ... worker processes sharing one PostgreSQL database, against the same T in one shard
//! (the single-process T). Reports per configuration the job's wall time, the CPU seconds of the
//! worker processes and of the database server, the shards and their solve time, the
//! coordination overhead (the worker CPU beyond the one-shard run's) and the parallel efficiency,
//! and checks that every run stored the same T bit for bit. Configurations are interleaved
//! (each repeat runs them all in turn) and medians reported.
//!
//!     cargo build -p helmholtz-server -p helmholtz-client -p helmholtz-tests --bins
//!     cargo run -p helmholtz-tests --bin helmholtz-scale -- --out scale.md
//!
//! Needs PostgreSQL (`HELMHOLTZ_TEST_POSTGRES`, default the local server with trust auth); the
//! database it creates is dropped at the end.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use helmholtz_tests::pg::{TestDatabase, WorkerProcess};
use helmholtz_tests::{ServerProcess, simulate_camera_session};
use serde_json::Value;

#[derive(Parser, Debug)]
#[command(
    name = "helmholtz-scale",
    about = "Scale benchmark: a camera session's T solved by 1, 2, 4 worker processes on one PostgreSQL database, against the one-shard T."
)]
struct Args {
    /// Projector side (the Bernoulli patterns are side x side).
    #[arg(long, default_value_t = 32)]
    projector: u32,
    /// Camera, WxH pixels.
    #[arg(long, default_value = "32x32")]
    camera: String,
    /// Frames (patterns) of the session.
    #[arg(long, default_value_t = 512)]
    frames: u64,
    /// Worker process counts to run, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    processes: Vec<usize>,
    /// Camera pixels per shard (`--transport-shard-pixels` of every worker).
    #[arg(long, default_value_t = 64)]
    shard_pixels: usize,
    /// Solver threads of each worker process (RAYON_NUM_THREADS): 1 makes each process stand
    /// for one core of its own, so the figures predict that many machines of one core.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Rounds; each round runs every configuration once, in turn.
    #[arg(long, default_value_t = 2)]
    repeats: usize,
    /// MiB of random bytes for the storage-layout comparison (bytea parts against large
    /// objects), in parts of --layout-part-kib; 0 skips it.
    #[arg(long, default_value_t = 128)]
    layout_mib: usize,
    /// KiB a part (an upload chunk or a part of T holds up to 8 MiB).
    #[arg(long, default_value_t = 1024)]
    layout_part_kib: usize,
    /// Also write the Markdown report to this file.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// CPU seconds (user + system) of process `pid`, and with `children` those of its reaped
/// children too.
fn cpu_seconds(pid: u32, children: bool) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let tick = |i: usize| fields.get(i).and_then(|v| v.parse::<u64>().ok());
    let mut ticks = tick(11)? + tick(12)?;
    if children {
        ticks += tick(13)? + tick(14)?;
    }
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    Some(ticks as f64 / hz)
}

/// CPU seconds of the local PostgreSQL server: its live processes, plus what the postmaster
/// has reaped from backends that ended.
fn postgres_cpu() -> f64 {
    let mut total = 0.0;
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return f64::NAN;
    };
    for e in entries.flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        let comm = std::fs::read_to_string(format!("/proc/{pid}/comm")).unwrap_or_default();
        if comm.trim() != "postgres" {
            continue;
        }
        let parent_is_postgres = std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .and_then(|s| {
                let ppid = s.rsplit_once(')')?.1.split_whitespace().nth(1)?.to_string();
                std::fs::read_to_string(format!("/proc/{ppid}/comm")).ok()
            })
            .is_some_and(|c| c.trim() == "postgres");
        total += cpu_seconds(pid, !parent_is_postgres).unwrap_or(0.0);
    }
    total
}

struct Config {
    name: String,
    processes: usize,
    shard_pixels: usize,
}

#[derive(Clone, Debug)]
struct Run {
    wall: f64,
    worker_cpu: f64,
    database_cpu: f64,
    shards: u64,
    solve_seconds: f64,
    model_seconds: f64,
    shard_workers: u64,
    t: Vec<u8>,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

async fn run(
    db: &TestDatabase,
    api: &ServerProcess,
    config: &Config,
    threads: usize,
) -> anyhow::Result<Run> {
    let threads = threads.to_string();
    let shard_pixels = config.shard_pixels.to_string();
    let env = [("RAYON_NUM_THREADS", threads.as_str())];
    let mut workers = Vec::new();
    for _ in 0..config.processes {
        workers.push(WorkerProcess::start_with_env(
            db,
            1,
            &["--transport-shard-pixels", &shard_pixels],
            &env,
        )?);
    }
    let cpu = |workers: &[WorkerProcess]| -> f64 {
        workers
            .iter()
            .map(|w| cpu_seconds(w.pid(), false).unwrap_or(f64::NAN))
            .sum()
    };
    let (worker0, database0) = (cpu(&workers), postgres_cpu());
    let http = helmholtz_tests::http_client();
    let r = http
        .post(api.url("/v1/sessions/cam/reconstructions"))
        .header("content-type", "application/json")
        .body(r#"{"method": "transport"}"#)
        .send()
        .await?;
    anyhow::ensure!(r.status() == 202, "request refused: {}", r.text().await?);
    let id = r.json::<Value>().await?["id"]
        .as_i64()
        .context("reconstruction id")?;
    let done = loop {
        let r: Value = http
            .get(api.url(&format!("/v1/reconstructions/{id}")))
            .send()
            .await?
            .json()
            .await?;
        match r["state"].as_str() {
            Some("done") => break r,
            Some("failed") | Some("cancelled") => bail!("reconstruction {id}: {r}"),
            _ => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    };
    let (worker1, database1) = (cpu(&workers), postgres_cpu());
    drop(workers);
    let wall_ms = db.scalar(&format!(
        "SELECT finished_ms - started_ms FROM jobs WHERE id = {id}"
    ));
    let shards = &done["report"]["details"]["shards"];
    Ok(Run {
        wall: wall_ms as f64 / 1e3,
        worker_cpu: worker1 - worker0,
        database_cpu: database1 - database0,
        shards: shards["count"].as_u64().unwrap_or(0),
        solve_seconds: shards["solve_seconds"].as_f64().unwrap_or(f64::NAN),
        model_seconds: shards["model_seconds"].as_f64().unwrap_or(f64::NAN),
        shard_workers: shards["workers"].as_u64().unwrap_or(0),
        t: db.transport(id),
    })
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.repeats >= 1, "--repeats must be at least 1");
    anyhow::ensure!(
        args.processes.iter().all(|&n| n >= 1),
        "--processes must be at least 1 each"
    );
    let (cw, ch) = args
        .camera
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
        .context("--camera is WxH, e.g. 32x32")?;
    let machine = {
        let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
        let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
        let load: Vec<&str> = load.split_whitespace().take(3).collect();
        format!(
            "{cores} cores, load average {} at the start",
            load.join(" ")
        )
    };
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader")?;
    let api = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"])?;
    eprintln!(
        "simulating the camera session ({}x{} projector, {} camera, {} frames)...",
        args.projector, args.projector, args.camera, args.frames
    );
    simulate_camera_session(&api, "cam", &args.camera, args.projector, args.frames);

    let mut configs = vec![Config {
        name: "1 process, one shard (the single-process T)".into(),
        processes: 1,
        shard_pixels: cw * ch,
    }];
    for &n in &args.processes {
        configs.push(Config {
            name: format!(
                "{n} process{}, shards of {} pixels",
                if n == 1 { "" } else { "es" },
                args.shard_pixels
            ),
            processes: n,
            shard_pixels: args.shard_pixels,
        });
    }
    let mut runs: Vec<Vec<Run>> = vec![Vec::new(); configs.len()];
    let started = Instant::now();
    for round in 0..args.repeats {
        for (c, config) in configs.iter().enumerate() {
            eprintln!(
                "round {} of {}: {}...",
                round + 1,
                args.repeats,
                config.name
            );
            let r = run(&db, &api, config, args.threads).await?;
            eprintln!(
                "  wall {:.2} s, worker CPU {:.2} s, database CPU {:.2} s, {} shards",
                r.wall, r.worker_cpu, r.database_cpu, r.shards
            );
            runs[c].push(r);
        }
    }
    let first = &runs[0][0].t;
    let identical = runs.iter().flatten().all(|r| &r.t == first);

    let base_cpu = median(runs[0].iter().map(|r| r.worker_cpu).collect());
    let one_process_wall = configs
        .iter()
        .zip(&runs)
        .find(|(c, _)| c.processes == 1 && c.shard_pixels == args.shard_pixels)
        .map(|(_, r)| median(r.iter().map(|r| r.wall).collect()));
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut md = String::new();
    use std::fmt::Write as _;
    writeln!(
        md,
        "- command: `helmholtz-scale --projector {} --camera {} --frames {} --processes {} --shard-pixels {} --threads {} --repeats {}`",
        args.projector,
        args.camera,
        args.frames,
        args.processes
            .iter()
            .map(|n| n.to_string())
            .collect::<Vec<_>>()
            .join(","),
        args.shard_pixels,
        args.threads,
        args.repeats
    )?;
    writeln!(md, "- machine: {machine}")?;
    writeln!(
        md,
        "- session: Lambertian scene, {p}x{p} projector ({k} unknowns a camera pixel), {} camera ({} pixels), {} Bernoulli frames",
        args.camera,
        cw * ch,
        args.frames,
        p = args.projector,
        k = args.projector * args.projector
    )?;
    writeln!(
        md,
        "- every worker process: `--workers 1`, RAYON_NUM_THREADS={}; medians of {} interleaved rounds; benchmark wall time {:.0} s",
        args.threads,
        args.repeats,
        started.elapsed().as_secs_f64()
    )?;
    writeln!(
        md,
        "- T stored by every run bit-for-bit identical: **{}** ({} bytes)",
        if identical { "yes" } else { "NO" },
        first.len()
    )?;
    writeln!(md)?;
    writeln!(
        md,
        "| configuration | wall s | worker CPU s | overhead vs one shard | database CPU s | shards (workers) | solve s a shard | model choice s | speedup vs 1 process | efficiency |"
    )?;
    writeln!(md, "|---|---|---|---|---|---|---|---|---|---|")?;
    for (config, r) in configs.iter().zip(&runs) {
        let wall = median(r.iter().map(|r| r.wall).collect());
        let cpu = median(r.iter().map(|r| r.worker_cpu).collect());
        let db_cpu = median(r.iter().map(|r| r.database_cpu).collect());
        let shards = r[0].shards;
        let workers = r.iter().map(|r| r.shard_workers).max().unwrap_or(0);
        let solve = median(
            r.iter()
                .map(|r| r.solve_seconds / r.shards.max(1) as f64)
                .collect(),
        );
        let model = median(r.iter().map(|r| r.model_seconds).collect());
        let (speedup, efficiency) = match one_process_wall {
            Some(w1) if config.shard_pixels == args.shard_pixels => {
                let s = w1 / wall;
                let used = config.processes.min(cores).max(1) as f64;
                (format!("{s:.2}"), format!("{:.0} %", 100.0 * s / used))
            }
            _ => ("".into(), "".into()),
        };
        writeln!(
            md,
            "| {} | {wall:.2} | {cpu:.2} | {:+.1} % | {db_cpu:.2} | {shards} ({workers}) | {solve:.3} | {model:.2} | {speedup} | {efficiency} |",
            config.name,
            100.0 * (cpu - base_cpu) / base_cpu,
        )?;
    }
    writeln!(md)?;
    writeln!(
        md,
        "Overhead: the worker processes' CPU seconds beyond the one-shard run's (claims, parts encoded and stored, frames re-read per shard, assembly, idle polling). Efficiency: speedup over the 1-process sharded run divided by the processes that can run at once (min(processes, {cores} cores))."
    )?;
    if args.layout_mib > 0 {
        writeln!(md)?;
        md.push_str(&layout(db.url(), args.layout_mib, args.layout_part_kib).await?);
    }
    print!("{md}");
    if let Some(out) = &args.out {
        std::fs::write(out, &md).with_context(|| format!("writing {}", out.display()))?;
    }
    if !identical {
        bail!("the stored T differs between runs");
    }
    Ok(())
}

/// Bulk data as `bytea` parts (rows of a table with `STORAGE EXTERNAL`, as the service stores
/// chunks, T and its shards' parts) against large objects (`lo_from_bytea` / `lo_get`): the same
/// random parts written, read whole, and read in 64 KiB slices (a frame's worth) through one
/// client connection; the space each takes.
async fn layout(url: &str, mib: usize, part_kib: usize) -> anyhow::Result<String> {
    use sqlx::{Connection, Executor, Row};
    let mut conn = sqlx::PgConnection::connect(url).await?;
    let part_bytes = part_kib.max(1) << 10;
    let parts = ((mib << 20) / part_bytes).max(1);
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let payload: Vec<Vec<u8>> = (0..parts)
        .map(|_| {
            (0..part_bytes / 8)
                .flat_map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    state.to_le_bytes()
                })
                .collect()
        })
        .collect();
    let total = (parts * part_bytes) as f64;
    conn.execute(
        "CREATE TABLE layout_bytea (part BIGINT PRIMARY KEY, data BYTEA NOT NULL); \
         ALTER TABLE layout_bytea ALTER COLUMN data SET STORAGE EXTERNAL; \
         CREATE TABLE layout_lo (part BIGINT PRIMARY KEY, oid OID NOT NULL)",
    )
    .await?;
    let lo_before: i64 = sqlx::query_scalar("SELECT pg_total_relation_size('pg_largeobject')")
        .fetch_one(&mut conn)
        .await?;
    let mb_s = |seconds: f64| total / 1e6 / seconds;
    let mut rows = Vec::new();
    // Writes, one transaction a part (as an append or a stored shard is).
    let t = Instant::now();
    for (i, p) in payload.iter().enumerate() {
        sqlx::query("INSERT INTO layout_bytea (part, data) VALUES ($1, $2)")
            .bind(i as i64)
            .bind(p)
            .execute(&mut conn)
            .await?;
    }
    let bytea_write = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for (i, p) in payload.iter().enumerate() {
        sqlx::query("INSERT INTO layout_lo (part, oid) VALUES ($1, lo_from_bytea(0, $2))")
            .bind(i as i64)
            .bind(p)
            .execute(&mut conn)
            .await?;
    }
    let lo_write = t.elapsed().as_secs_f64();
    rows.push((
        "write, a part a transaction",
        mb_s(bytea_write),
        mb_s(lo_write),
    ));
    // Whole parts read back in order (a pass over the frames), checked.
    let t = Instant::now();
    for (i, p) in payload.iter().enumerate() {
        let data: Vec<u8> = sqlx::query("SELECT data FROM layout_bytea WHERE part = $1")
            .bind(i as i64)
            .fetch_one(&mut conn)
            .await?
            .get(0);
        anyhow::ensure!(&data == p, "bytea part {i} read back differs");
    }
    let bytea_read = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for (i, p) in payload.iter().enumerate() {
        let data: Vec<u8> = sqlx::query("SELECT lo_get(oid) FROM layout_lo WHERE part = $1")
            .bind(i as i64)
            .fetch_one(&mut conn)
            .await?
            .get(0);
        anyhow::ensure!(&data == p, "large object {i} read back differs");
    }
    let lo_read = t.elapsed().as_secs_f64();
    rows.push(("read whole parts", mb_s(bytea_read), mb_s(lo_read)));
    // 64 KiB slices of every part (one frame of a 128x128 f32 camera).
    let slice = (64usize << 10).min(part_bytes);
    let slices = part_bytes / slice;
    let t = Instant::now();
    for i in 0..parts {
        for j in 0..slices {
            let _: Vec<u8> = sqlx::query(
                "SELECT substring(data FROM $2 FOR $3) FROM layout_bytea WHERE part = $1",
            )
            .bind(i as i64)
            .bind((j * slice + 1) as i32)
            .bind(slice as i32)
            .fetch_one(&mut conn)
            .await?
            .get(0);
        }
    }
    let bytea_slices = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for i in 0..parts {
        for j in 0..slices {
            let _: Vec<u8> =
                sqlx::query("SELECT lo_get(oid, $2, $3) FROM layout_lo WHERE part = $1")
                    .bind(i as i64)
                    .bind((j * slice) as i64)
                    .bind(slice as i32)
                    .fetch_one(&mut conn)
                    .await?
                    .get(0);
        }
    }
    let lo_slices = t.elapsed().as_secs_f64();
    rows.push(("read in 64 KiB slices", mb_s(bytea_slices), mb_s(lo_slices)));
    let bytea_size: i64 = sqlx::query_scalar("SELECT pg_total_relation_size('layout_bytea')")
        .fetch_one(&mut conn)
        .await?;
    let lo_after: i64 = sqlx::query_scalar("SELECT pg_total_relation_size('pg_largeobject')")
        .fetch_one(&mut conn)
        .await?;
    let lo_table: i64 = sqlx::query_scalar("SELECT pg_total_relation_size('layout_lo')")
        .fetch_one(&mut conn)
        .await?;
    conn.execute(
        "SELECT lo_unlink(oid) FROM layout_lo; DROP TABLE layout_lo; DROP TABLE layout_bytea",
    )
    .await?;
    conn.close().await.ok();
    let mut md = String::new();
    use std::fmt::Write as _;
    writeln!(
        md,
        "Storage layout: {parts} random parts of {part_kib} KiB ({:.0} MB), one client connection, MB/s of payload:",
        total / 1e6
    )?;
    writeln!(md)?;
    writeln!(
        md,
        "| operation | bytea parts (STORAGE EXTERNAL) | large objects |"
    )?;
    writeln!(md, "|---|---|---|")?;
    for (name, b, l) in rows {
        writeln!(md, "| {name} | {b:.0} | {l:.0} |")?;
    }
    writeln!(
        md,
        "| space on disk / payload | {:.3} | {:.3} |",
        bytea_size as f64 / total,
        (lo_after - lo_before + lo_table) as f64 / total
    )?;
    Ok(md)
}
