//! `sdhop-serve`: the SD-HOP HTTP inference service. Starts with no
//! arguments on a fresh clone: loads every model in `models/` and listens on
//! 127.0.0.1:8080. Every setting is a flag and an environment variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::{Parser, ValueEnum};
use prometheus::Registry;
use sdhop::backend::{select, BackendChoice, GpuOptions};
use sdhop::http::conn::ConnLimits;
use sdhop::http::image::ImageLimits;
use sdhop::http::state::DEFAULT_MESH_LIMITS;
use sdhop::http::{load_models, serve, warm_up, AppState, HttpConfig};
use sdhop::infer::{Infer, InferConfig, InferMetrics};
use sdhop::pose::MeshLimits;

/// mimalloc keeps freed pages for the next request instead of handing them
/// back and faulting them in again: the pyramids, edge lists and masks of
/// every detection are large short-lived buffers (50 -> 44 ms per
/// photograph with one model on one thread). After a large mesh the pose
/// pool asks it to hand its freed pages back (`mi_collect`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

/// SD-HOP occlusion-aware detection over HTTP (see openapi.yaml).
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Address to listen on.
    #[arg(long, env = "SDHOP_ADDR", default_value = "127.0.0.1:8080")]
    addr: SocketAddr,
    /// Folder of weights files (*.safetensors); every one is loaded.
    #[arg(long, env = "SDHOP_MODELS_DIR", default_value = "models")]
    models_dir: PathBuf,
    /// /detect requests waiting at most; more are answered 503 with
    /// Retry-After.
    #[arg(long, env = "SDHOP_QUEUE_SIZE", default_value_t = 32)]
    queue_size: usize,
    /// Requests computed together at most.
    #[arg(long, env = "SDHOP_MAX_BATCH", default_value_t = 4)]
    max_batch: usize,
    /// How long the worker waits to fill a batch, in milliseconds.
    #[arg(long, env = "SDHOP_MAX_BATCH_DELAY_MS", default_value_t = 2)]
    max_batch_delay_ms: u64,
    /// Deadline of a request without `timeout_ms`, in milliseconds.
    #[arg(long, env = "SDHOP_TIMEOUT_MS", default_value_t = 30_000)]
    timeout_ms: u64,
    /// Largest `timeout_ms` a request may ask for.
    #[arg(long, env = "SDHOP_MAX_TIMEOUT_MS", default_value_t = 300_000)]
    max_timeout_ms: u64,
    /// Largest request body of /detect, in bytes.
    #[arg(long, env = "SDHOP_MAX_BODY_BYTES", default_value_t = 20 << 20)]
    max_body_bytes: usize,
    /// Largest request body of POST /pose (image, mesh and mask).
    #[arg(long, env = "SDHOP_MAX_POSE_BODY_BYTES", default_value_t = 64 << 20)]
    max_pose_body_bytes: usize,
    /// Most vertices of a POST /pose mesh: the count its file declares is
    /// checked (against this and against its bytes) before anything is
    /// allocated; more is answered 413.
    #[arg(long, env = "SDHOP_MAX_MESH_VERTICES", default_value_t = DEFAULT_MESH_LIMITS.max_vertices)]
    max_mesh_vertices: usize,
    /// Most triangles of a POST /pose mesh (polygons count as the
    /// triangles they fan into), checked as the vertices are.
    #[arg(long, env = "SDHOP_MAX_MESH_TRIANGLES", default_value_t = DEFAULT_MESH_LIMITS.max_triangles)]
    max_mesh_triangles: usize,
    /// POST /pose requests admitted at once (waiting or computing), in a
    /// lane of their own: more are answered 503 with Retry-After while
    /// /detect is still served and readiness stays 200 (the lane's
    /// occupancy is in /metrics, for an autoscaler).
    #[arg(long, env = "SDHOP_POSE_QUEUE_SIZE", default_value_t = 8)]
    pose_queue_size: usize,
    /// Threads of the pose pool, which refines poses (0: one per core). They
    /// run at a lower priority (niceness +10) than /detect's, so that
    /// detections keep the cores while both compute.
    #[arg(long, env = "SDHOP_POSE_THREADS", default_value_t = 0)]
    pose_threads: usize,
    /// Memory, in MiB, that the requests being decoded, waiting and
    /// computed may take together: each reserves its estimated cost (from
    /// the image's declared size and the models' pyramids) before its image
    /// is decoded and waits its turn when the budget is taken. 0: the
    /// container's memory limit less 1024 MiB, or 1536 MiB without one
    /// (safe under the manifest's 2560 MiB limit).
    #[arg(long, env = "SDHOP_MEMORY_BUDGET_MB", default_value_t = 0)]
    memory_budget_mb: u64,
    /// Pixels a batch of detections holds at most: a larger image is
    /// computed in a batch of its own, so that small images batched with
    /// it do not wait for it.
    #[arg(long, env = "SDHOP_MAX_BATCH_PIXELS", default_value_t = sdhop::infer::DEFAULT_MAX_BATCH_PIXELS)]
    max_batch_pixels: usize,
    /// Largest image, in pixels (checked from the header, before decoding).
    #[arg(long, env = "SDHOP_MAX_PIXELS", default_value_t = 16_000_000)]
    max_pixels: usize,
    /// Longest image side, in pixels.
    #[arg(long, env = "SDHOP_MAX_SIDE", default_value_t = 16_384)]
    max_side: u32,
    /// Compute backend: `auto` takes a real GPU when there is one (a
    /// software adapter such as llvmpipe counts as none) and the CPU
    /// otherwise; `gpu` insists on a GPU adapter (software ones included)
    /// and fails without one; `cpu` never looks for one.
    #[arg(long, env = "SDHOP_BACKEND", value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Largest `max_detections` a request may ask for.
    #[arg(long, env = "SDHOP_MAX_DETECTIONS", default_value_t = 100)]
    max_detections: usize,
    /// Threads of the async runtime (HTTP, decoding hand-off).
    #[arg(long, env = "SDHOP_HTTP_THREADS", default_value_t = 2)]
    http_threads: usize,
    /// Threads of the compute pool (0: one per core).
    #[arg(long, env = "SDHOP_COMPUTE_THREADS", default_value_t = 0)]
    compute_threads: usize,
    /// A request body must arrive at least this fast, in bytes per second
    /// on average once --body-grace-ms has passed (0: only the deadline);
    /// a slower or stalled upload is answered 408 and closed.
    #[arg(long, env = "SDHOP_MIN_BODY_RATE", default_value_t = 16 << 10)]
    min_body_rate: u64,
    /// How long a request body may take before --min-body-rate applies.
    #[arg(long, env = "SDHOP_BODY_GRACE_MS", default_value_t = 5000)]
    body_grace_ms: u64,
    /// Open connections at most; more are answered 503 and closed.
    #[arg(long, env = "SDHOP_MAX_CONNECTIONS", default_value_t = 512)]
    max_connections: usize,
    /// Open connections from one client address at most; more are
    /// answered 429 and closed.
    #[arg(long, env = "SDHOP_MAX_CONNECTIONS_PER_CLIENT", default_value_t = 128)]
    max_connections_per_client: usize,
    /// Seconds to finish requests in flight after SIGTERM (after the
    /// drain, --drain-seconds) or Ctrl-C: the service stops accepting
    /// connections and admits nothing new; requests still waiting when the
    /// period ends, and bodies still arriving, are answered 503 just
    /// before it does.
    #[arg(long, env = "SDHOP_GRACE_SECONDS", default_value_t = 30)]
    grace_seconds: u64,
    /// Seconds to keep serving after SIGTERM before the grace period: readiness
    /// answers 503 while connections are still accepted and requests
    /// answered, so that requests routed here before the orchestrator's
    /// endpoints update are served rather than refused (Kubernetes sends
    /// SIGTERM and updates its endpoints at the same time). Ctrl-C
    /// (SIGINT), or a second signal, skips the drain.
    #[arg(long, env = "SDHOP_DRAIN_SECONDS", default_value_t = 5.0)]
    drain_seconds: f64,
    /// Log format.
    #[arg(long, env = "SDHOP_LOG_FORMAT", value_enum, default_value = "text")]
    log_format: LogFormat,
    /// Do not serve: ask the server at --addr whether it is ready and exit
    /// 0 if so, 1 if not (a container health check needing no curl).
    #[arg(long)]
    check_ready: bool,
}

/// `GET /health/ready` on the server at `addr` (an unspecified address
/// means this host); true on a 200.
fn check_ready(addr: SocketAddr) -> bool {
    use std::io::{Read, Write};
    let mut target = addr;
    if target.ip().is_unspecified() {
        target.set_ip(std::net::Ipv4Addr::LOCALHOST.into());
    }
    let timeout = Duration::from_secs(3);
    let Ok(mut stream) = std::net::TcpStream::connect_timeout(&target, timeout) else {
        return false;
    };
    let _ = stream.set_read_timeout(Some(timeout));
    let request = "GET /health/ready HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n";
    if stream.write_all(request.as_bytes()).is_err() {
        return false;
    }
    let mut head = [0u8; 16];
    let n = stream.read(&mut head).unwrap_or(0);
    head[..n].starts_with(b"HTTP/1.1 200")
}

fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("SDHOP_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().flatten_event(true).init(),
    }
}

/// The signal that asked the service to stop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stop {
    Terminate,
    Interrupt,
}

/// Resolves on SIGTERM or Ctrl-C, saying which.
async fn stop_signal() -> Stop {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => Stop::Interrupt,
        () = term => Stop::Terminate,
    }
}

/// Resolves when the service should stop taking connections: on Ctrl-C at
/// once; on SIGTERM after `drain` of serving while not ready (cut short by
/// a second signal).
async fn shutdown_signal(state: Arc<AppState>, drain: Duration) {
    let first = stop_signal().await;
    if first == Stop::Interrupt || drain.is_zero() {
        return;
    }
    state.begin_drain();
    tracing::info!(
        "SIGTERM: draining for {:.1} s (not ready, still serving)",
        drain.as_secs_f64()
    );
    tokio::select! {
        () = tokio::time::sleep(drain) => {}
        stop = stop_signal() => tracing::info!("{stop:?} during the drain: stopping now"),
    }
}

fn main() -> ExitCode {
    sdhop::infer::memory::keep_freed_pages();
    let args = Args::parse();
    if args.check_ready {
        return if check_ready(args.addr) {
            ExitCode::SUCCESS
        } else {
            ExitCode::FAILURE
        };
    }
    init_logging(args.log_format);
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> Result<(), String> {
    // The compute pool, its threads named (in `top -H` and /proc).
    rayon::ThreadPoolBuilder::new()
        .num_threads(args.compute_threads)
        .thread_name(|i| format!("sdhop-compute-{i}"))
        .build_global()
        .map_err(|e| e.to_string())?;
    let drain = Duration::try_from_secs_f64(args.drain_seconds).map_err(|_| {
        format!(
            "--drain-seconds {}: give a number of seconds, 0 or more",
            args.drain_seconds
        )
    })?;
    let models = load_models(&args.models_dir).map_err(|e| e.to_string())?;
    let registry = Registry::new();
    let (backend, why_not_gpu) =
        select(args.backend, &GpuOptions::default()).map_err(|e| format!("--backend gpu: {e}"))?;
    if let Some(why) = why_not_gpu {
        tracing::info!(reason = %why, "no usable GPU; running on the CPU backend");
    }
    let infer_config = InferConfig {
        queue_size: args.queue_size,
        max_batch: args.max_batch,
        max_batch_delay: Duration::from_millis(args.max_batch_delay_ms),
        pose_queue_size: args.pose_queue_size.max(1),
        pose_threads: if args.pose_threads > 0 {
            args.pose_threads
        } else {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        },
        memory_budget_bytes: if args.memory_budget_mb > 0 {
            args.memory_budget_mb.saturating_mul(1 << 20)
        } else {
            sdhop::infer::budget::default_budget_bytes()
        },
        max_batch_pixels: args.max_batch_pixels.max(1),
    };
    let metrics = InferMetrics::new(&registry).map_err(|e| e.to_string())?;
    let infer = Infer::start(backend, infer_config, metrics).map_err(|e| e.to_string())?;
    let config = HttpConfig {
        max_body_bytes: args.max_body_bytes,
        max_pose_body_bytes: args.max_pose_body_bytes,
        image: ImageLimits {
            max_pixels: args.max_pixels,
            max_side: args.max_side,
        },
        mesh: MeshLimits {
            max_vertices: args.max_mesh_vertices,
            max_triangles: args.max_mesh_triangles,
        },
        default_timeout: Duration::from_millis(args.timeout_ms),
        max_timeout: Duration::from_millis(args.max_timeout_ms.max(args.timeout_ms)),
        max_detections: args.max_detections,
        min_body_rate: args.min_body_rate,
        body_grace: Duration::from_millis(args.body_grace_ms),
        connections: ConnLimits {
            max_total: args.max_connections.max(1),
            max_per_client: args.max_connections_per_client.max(1),
        },
    };
    let names: Vec<&str> = models.iter().map(|m| m.model.meta.name.as_str()).collect();
    tracing::info!(
        models = ?names,
        backend = %infer.backend_info().kind,
        device = %infer.backend_info().device,
        "loaded {} models from {}",
        models.len(),
        args.models_dir.display()
    );
    let state = AppState::new(infer, models, config, registry).map_err(|e| e.to_string())?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(args.http_threads.max(1))
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let result = runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(args.addr)
            .await
            .map_err(|e| format!("cannot listen on {}: {e}", args.addr))?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        // The first line on stdout, for scripts and tests that pick port 0.
        println!("listening on {addr}");
        tracing::info!("listening on {addr}");
        let warm = Arc::clone(&state);
        tokio::spawn(async move {
            let t = std::time::Instant::now();
            match warm_up(&warm).await {
                Ok(()) => {
                    tracing::info!("ready ({:.0} ms warm-up)", t.elapsed().as_secs_f64() * 1e3)
                }
                Err(e) => tracing::error!("warm-up failed, staying not ready: {e}"),
            }
        });
        let grace = Duration::from_secs(args.grace_seconds);
        let signal = shutdown_signal(Arc::clone(&state), drain);
        let clean = serve(listener, state, signal, grace)
            .await
            .map_err(|e| e.to_string())?;
        if clean {
            tracing::info!("stopped");
        } else {
            tracing::warn!("stopped after the grace period with work unfinished");
        }
        Ok(())
    });
    // Dropping the runtime would wait for blocking tasks (a worker join
    // still pending after the grace period): leave them behind instead.
    runtime.shutdown_timeout(Duration::from_millis(100));
    result
}
