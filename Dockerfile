# The fleetslam server. Build: `docker build -t fleetslam .`; run with docker-compose.yml
# (PostgreSQL) or alone on the embedded SQLite store in /data.
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY . .
RUN cargo build --release --locked -p fleetslam-cli \
    && cp target/release/fleetslam /usr/local/bin/fleetslam

FROM debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --home /data fleetslam \
    && mkdir -p /data && chown fleetslam /data
COPY --from=build /usr/local/bin/fleetslam /usr/local/bin/fleetslam
COPY web /app/web
USER fleetslam
ENV FLEETSLAM_BIND=0.0.0.0:8080 \
    FLEETSLAM_DATA_DIR=/data \
    FLEETSLAM_WEB_DIR=/app/web
EXPOSE 8080
VOLUME ["/data"]
HEALTHCHECK --interval=10s --timeout=3s CMD ["fleetslam", "runs", "--server", "http://127.0.0.1:8080", "--limit", "1"]
ENTRYPOINT ["fleetslam"]
CMD ["serve"]
