# sdhop-serve: the SD-HOP inference service, with the shipped models.
# The build is the one .ci/run does: cargo, release profile, Cargo.lock.
FROM rust:1-slim-bookworm AS build
WORKDIR /src
# Dependency layer, cached until Cargo.toml or Cargo.lock change: build the
# dependencies against stub targets.
COPY Cargo.toml Cargo.lock ./
RUN mkdir -p src/bin benches \
 && touch src/lib.rs \
 && echo "fn main() {}" > src/bin/sdhop-train.rs \
 && echo "fn main() {}" > src/bin/sdhop-serve.rs \
 && echo "fn main() {}" > benches/detect.rs \
 && echo "fn main() {}" > benches/backends.rs \
 && echo "fn main() {}" > benches/pose.rs \
 && echo "fn main() {}" > benches/ko8_speed.rs \
 && cargo build --release --locked --bins \
 && rm -rf src benches
COPY src ./src
COPY benches ./benches
COPY kernels ./kernels
COPY openapi.yaml ./
# The learned cells' backbone and projection are built into the binaries
# (include_bytes!).
COPY models/backbones ./models/backbones
RUN touch src/lib.rs src/bin/*.rs && cargo build --release --locked --bins

FROM debian:bookworm-slim
# The Vulkan loader, for the GPU backend where the runtime provides a GPU
# and its driver (e.g. the NVIDIA container toolkit); without one the
# service runs on the CPU.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libvulkan1 \
 && rm -rf /var/lib/apt/lists/*
RUN useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin sdhop
COPY --from=build /src/target/release/sdhop-serve /src/target/release/sdhop-train /usr/local/bin/
COPY models /opt/sdhop/models
USER 10001
ENV SDHOP_ADDR=0.0.0.0:8080 \
    SDHOP_MODELS_DIR=/opt/sdhop/models \
    SDHOP_LOG_FORMAT=json
EXPOSE 8080
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
  CMD ["sdhop-serve", "--check-ready"]
ENTRYPOINT ["sdhop-serve"]
