# syntax=docker/dockerfile:1
# The `kairos` binary in a small runtime image (CPU). Build from the repository root:
#   docker build -t kairos:0.1.0 .
# The CUDA variant (Candle's CUDA kernels, `--features cuda`) is in docs/DEPLOY.md. This file was
# not built on the machines this repository is developed on (no container daemon there); a test
# (server/tests/it/deploy.rs) checks what can be checked without one: every path it copies
# exists, and the binary, subcommand and flags it runs exist.

FROM rust:1.95-bookworm AS build
WORKDIR /src
# The workspace: every member's manifest must be present for Cargo to load it.
COPY Cargo.toml Cargo.lock ./
COPY engine engine
COPY server server
COPY sdk sdk
COPY tests tests
# Read at compile time: the policy interfaces (plugin host bindings) and the plots' font.
COPY wit wit
COPY assets assets
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked -p kairos-cli --bin kairos \
    && cp target/release/kairos /usr/local/bin/kairos

FROM debian:bookworm-slim
RUN useradd --uid 10001 --no-create-home --shell /usr/sbin/nologin kairos \
    && mkdir -p /var/lib/kairos && chown kairos /var/lib/kairos
COPY --from=build /usr/local/bin/kairos /usr/local/bin/kairos
USER 10001
# QUIC (robots and workers) and plain-HTTP metrics and readiness.
EXPOSE 4433/udp 9464/tcp
ENTRYPOINT ["kairos"]
CMD ["serve", "--listen=0.0.0.0:4433", "--data-dir=/var/lib/kairos", "--metrics-listen=0.0.0.0:9464"]
