//! What the HTTP tests share: a synthetic model made once per test
//! process, synthetic scenes, an in-process server on an ephemeral port,
//! and the real binary.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Cursor};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;

use prometheus::Registry;
use reqwest::StatusCode;
use sdhop::backend::CpuBackend;
use sdhop::http::{load_models, serve, warm_up, AppState, HttpConfig};
use sdhop::infer::{Infer, InferConfig, InferMetrics};
use sdhop::synth::{hand_model, scene, HandModelParams, Scene, SceneParams, SynthObject};

pub const OBJECT: SynthObject = SynthObject {
    cols: 12,
    rows: 10,
    seed: 11,
};

/// A folder holding the synthetic model, made once per test process.
pub fn models_dir() -> PathBuf {
    static DIR: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("sdhop-http-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
        model.save(&dir.join("synthetic.safetensors")).unwrap();
        dir
    })
    .clone()
}

pub fn synthetic_scene(seed: u64, width: usize, height: usize) -> Scene {
    scene(
        &OBJECT,
        &SceneParams {
            seed,
            width,
            height,
            ..SceneParams::default()
        },
    )
    .unwrap()
}

pub fn encode(scene: &Scene, format: image::ImageFormat) -> Vec<u8> {
    let mut out = Vec::new();
    scene
        .image
        .to_rgb8()
        .write_to(&mut Cursor::new(&mut out), format)
        .unwrap();
    out
}

/// A running in-process server.
pub struct Server {
    pub base: String,
    pub stop: Option<tokio::sync::oneshot::Sender<()>>,
    pub done: Option<tokio::task::JoinHandle<std::io::Result<bool>>>,
}

impl Server {
    pub async fn start(queue: InferConfig, http: HttpConfig) -> Self {
        let registry = Registry::new();
        let metrics = InferMetrics::new(&registry).unwrap();
        let infer = Infer::start(Box::new(CpuBackend), queue, metrics).unwrap();
        let models = load_models(&models_dir()).unwrap();
        let state = AppState::new(infer, models, http, registry).unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let s = Arc::clone(&state);
        let done = tokio::spawn(async move {
            serve(
                listener,
                s,
                async {
                    let _ = rx.await;
                },
                Duration::from_secs(30),
            )
            .await
        });
        warm_up(&state).await.unwrap();
        Server {
            base,
            stop: Some(tx),
            done: Some(done),
        }
    }

    pub async fn default() -> Self {
        Self::start(InferConfig::default(), HttpConfig::default()).await
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn stop(mut self) -> bool {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        match self.done.take() {
            Some(d) => d.await.unwrap().unwrap(),
            None => true,
        }
    }
}

/// Starts the real binary on port 0; returns the child and its address.
pub fn spawn_binary(extra: &[&str]) -> (std::process::Child, String) {
    spawn_binary_env(extra, &[])
}

/// [`spawn_binary`] with extra environment variables.
pub fn spawn_binary_env(extra: &[&str], envs: &[(&str, &str)]) -> (std::process::Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_sdhop-serve"))
        .args(["--addr", "127.0.0.1:0", "--models-dir"])
        .arg(models_dir())
        .args(extra)
        .envs(envs.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap()
        .to_string();
    (child, format!("http://{addr}"))
}

pub async fn wait_ready(base: &str) {
    for _ in 0..600 {
        if let Ok(r) = reqwest::get(format!("{base}/health/ready")).await {
            if r.status() == StatusCode::OK {
                return;
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("the server never became ready");
}

/// The server's `/metrics` text.
pub async fn metrics_text(base: &str) -> String {
    reqwest::get(format!("{base}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

/// Waits at most `within` until the server's `/metrics` holds `line`;
/// returns the text that did.
pub async fn wait_for_metric(base: &str, line: &str, within: Duration) -> String {
    let t = std::time::Instant::now();
    loop {
        let text = metrics_text(base).await;
        if text.contains(line) {
            return text;
        }
        assert!(t.elapsed() < within, "no {line} within {within:?}: {text}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
