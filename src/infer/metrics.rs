//! Prometheus metrics of the queue (prefix `sdhop_`, bounded label values).

use prometheus::{
    GaugeVec, Histogram, HistogramOpts, IntCounterVec, IntGauge, IntGaugeVec, Opts, Registry,
};

use super::Lane;

/// The queue's metrics, registered in the service's registry.
#[derive(Clone)]
pub struct InferMetrics {
    pub queue_size: IntGauge,
    pub queue_duration: Histogram,
    pub compute_duration: Histogram,
    pub batch_size: Histogram,
    /// Requests by outcome: completed, failed, expired, cancelled, rejected.
    pub jobs: IntCounterVec,
    pub backend_healthy: IntGauge,
    /// Places taken per lane (detect: waiting for the worker; pose:
    /// admitted and not yet answered).
    pub lane_taken: IntGaugeVec,
    /// Places per lane: a lane is saturated when every one is taken.
    pub lane_capacity: IntGaugeVec,
    /// Requests refused because their lane was full.
    pub lane_rejected: IntCounterVec,
    /// Share of each lane's places taken (0 to 1; 1: saturated, its
    /// requests are refused 503): what an autoscaler scales on
    /// (deploy/sdhop-hpa-queue.yaml).
    pub lane_occupancy: GaugeVec,
}

/// Latency buckets in seconds, 1 ms to 60 s.
const SECONDS: [f64; 14] = [
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 60.0,
];

impl InferMetrics {
    pub fn new(registry: &Registry) -> Result<Self, prometheus::Error> {
        let m = Self {
            queue_size: IntGauge::new("sdhop_queue_size", "Requests waiting in the queue")?,
            queue_duration: Histogram::with_opts(
                HistogramOpts::new(
                    "sdhop_queue_duration_seconds",
                    "Time requests waited in the queue",
                )
                .buckets(SECONDS.to_vec()),
            )?,
            compute_duration: Histogram::with_opts(
                HistogramOpts::new(
                    "sdhop_compute_duration_seconds",
                    "Time from a batch's start to a request's answer",
                )
                .buckets(SECONDS.to_vec()),
            )?,
            batch_size: Histogram::with_opts(
                HistogramOpts::new("sdhop_batch_size", "Requests computed together")
                    .buckets(vec![1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0]),
            )?,
            jobs: IntCounterVec::new(
                Opts::new("sdhop_queue_requests_total", "Queued requests by outcome"),
                &["outcome"],
            )?,
            backend_healthy: IntGauge::new(
                "sdhop_backend_healthy",
                "1 while the compute backend works",
            )?,
            lane_taken: IntGaugeVec::new(
                Opts::new(
                    "sdhop_lane_taken",
                    "Places taken per lane (detect: waiting for the worker; pose: admitted, not yet answered)",
                ),
                &["lane"],
            )?,
            lane_capacity: IntGaugeVec::new(
                Opts::new(
                    "sdhop_lane_capacity",
                    "Places per lane; the lane is saturated when all are taken",
                ),
                &["lane"],
            )?,
            lane_rejected: IntCounterVec::new(
                Opts::new(
                    "sdhop_lane_rejected_total",
                    "Requests refused because their lane was full",
                ),
                &["lane"],
            )?,
            lane_occupancy: GaugeVec::new(
                Opts::new(
                    "sdhop_lane_occupancy",
                    "Share of each lane's places taken, 0 to 1 (1: saturated, its requests are answered 503)",
                ),
                &["lane"],
            )?,
        };
        for lane in Lane::ALL {
            m.set_lane(lane, 0);
            m.lane_rejected.with_label_values(&[lane.name()]);
        }
        registry.register(Box::new(m.queue_size.clone()))?;
        registry.register(Box::new(m.queue_duration.clone()))?;
        registry.register(Box::new(m.compute_duration.clone()))?;
        registry.register(Box::new(m.batch_size.clone()))?;
        registry.register(Box::new(m.jobs.clone()))?;
        registry.register(Box::new(m.backend_healthy.clone()))?;
        registry.register(Box::new(m.lane_taken.clone()))?;
        registry.register(Box::new(m.lane_capacity.clone()))?;
        registry.register(Box::new(m.lane_rejected.clone()))?;
        registry.register(Box::new(m.lane_occupancy.clone()))?;
        Ok(m)
    }

    /// `taken` places of `lane` are taken now.
    pub fn set_lane(&self, lane: Lane, taken: usize) {
        if lane == Lane::Detect {
            self.queue_size.set(taken as i64);
        }
        self.lane_taken
            .with_label_values(&[lane.name()])
            .set(taken as i64);
        let places = self.lane_capacity.with_label_values(&[lane.name()]).get();
        self.lane_occupancy
            .with_label_values(&[lane.name()])
            .set(if places > 0 {
                (taken as f64 / places as f64).min(1.0)
            } else {
                0.0
            });
    }

    pub fn set_capacity(&self, lane: Lane, places: usize) {
        self.lane_capacity
            .with_label_values(&[lane.name()])
            .set(places as i64);
        let taken = self.lane_taken.with_label_values(&[lane.name()]).get();
        self.set_lane(lane, taken.max(0) as usize);
    }

    /// One request refused because `lane` was full.
    pub fn reject(&self, lane: Lane) {
        self.lane_rejected.with_label_values(&[lane.name()]).inc();
    }

    /// Counts one request with `outcome`.
    pub fn job(&self, outcome: &str) {
        self.jobs.with_label_values(&[outcome]).inc();
    }
}
