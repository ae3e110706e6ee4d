# One container per station: `mvpose serve` on the station file mounted at /etc/mvpose/station.yaml.
# tests/test_dockerfile.py runs this file's `npm ci` and `pip install` commands (a fresh node_modules,
# a fresh virtual environment), because no Docker engine runs on our build machines; keep every
# install step a RUN line below.

# The operator page's front-end libraries (htmx, uPlot, Swagger UI), from the npm registry,
# pinned by server/web/package-lock.json; copied into the package before pip installs it.
FROM node:20-slim AS web
WORKDIR /web
COPY server/web/package.json server/web/package-lock.json ./
RUN npm ci --ignore-scripts --no-audit --no-fund --prefer-offline

# The OPC UA link's Machine Vision information model: the OPC Foundation's NodeSet2 files from
# the npm package node-opcua-nodesets, pinned by its package-lock.json (checked by SHA256SUMS).
FROM node:20-slim AS nodesets
WORKDIR /nodesets
COPY drivers/links/opcua_nodesets/package.json drivers/links/opcua_nodesets/package-lock.json ./
RUN npm ci --ignore-scripts --no-audit --no-fund --prefer-offline

FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MVPOSE_STATION=/etc/mvpose/station.yaml \
    MVPOSE_DATA_DIR=/var/lib/mvpose \
    MVPOSE_HOST=0.0.0.0 \
    MVPOSE_PORT=8000 \
    MVPOSE_PLC_HOST=0.0.0.0 \
    MVPOSE_PLC_PORT=5020

# A fixed uid so the named volume for the store and the image archive has a known owner.
RUN groupadd --system --gid 10001 mvpose \
    && useradd --system --uid 10001 --gid mvpose --home-dir /var/lib/mvpose --create-home mvpose

WORKDIR /opt/mvpose
COPY pyproject.toml README.md ./
COPY mvpose_core ./mvpose_core
COPY drivers ./drivers
COPY server ./server
COPY --from=web /web/node_modules ./server/web/node_modules
COPY --from=nodesets /nodesets/node_modules ./drivers/links/opcua_nodesets/node_modules
# The operator page's message catalogues, compiled (.po → .mo) before the package is installed
# with them; Babel is pinned as in pyproject.toml.
RUN python -m pip install --no-cache-dir "babel==2.18.0" \
    && python -m babel.messages.frontend compile -d server/web/locale
# postgres: the psycopg driver for plants that collect every station in one PostgreSQL database.
RUN python -m pip install --no-cache-dir ".[postgres]"
COPY deploy/stations /etc/mvpose/examples

USER mvpose
VOLUME ["/var/lib/mvpose"]
# 8000 REST API; 5020 Modbus/TCP (an unprivileged port: the compose file maps the PLC's 502 onto it);
# 4840 OPC UA when the station file enables it.
EXPOSE 8000 5020 4840

# Liveness only: readiness (cameras, PLC link) is for the line's monitoring, not for restarts.
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/api/v1/health/live' % os.environ.get('MVPOSE_PORT', '8000'), timeout=2)"]

ENTRYPOINT ["mvpose", "serve"]
CMD ["--station", "/etc/mvpose/station.yaml"]
