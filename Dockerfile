# Builds the sdhop command-line tool (the HTTP server is a later issue).
# Same build as .ci/run: cargo, release profile.
FROM rust:1-slim-bookworm AS build
WORKDIR /src
# Cache dependencies: build them against a stub crate first.
COPY Cargo.toml Cargo.lock ./
RUN mkdir -p src/bin benches && echo "" > src/lib.rs \
 && echo "fn main() {}" > src/bin/sdhop-train.rs && echo "fn main() {}" > benches/detect.rs \
 && cargo build --release --locked && rm -rf src benches
COPY src ./src
COPY benches ./benches
RUN touch src/lib.rs && cargo build --release --locked --bin sdhop-train

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --create-home sdhop
COPY --from=build /src/target/release/sdhop-train /usr/local/bin/sdhop-train
COPY models /opt/sdhop/models
USER sdhop
WORKDIR /home/sdhop
ENTRYPOINT ["sdhop-train"]
CMD ["demo", "--out", "/home/sdhop/demo"]
