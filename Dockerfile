# cranetwin service image: the API (uvicorn), the UDP ingest daemon and the simulated fleet all run
# from this one image with different commands (see docker-compose.yml).
#
#   docker build -t cranetwin .
#   docker run --rm -p 8000:8000 cranetwin            # API on the embedded SQLite database
#
# The web UI's static files (web/) are copied next to the package and found through
# CRANETWIN_WEB_DIR (a regular, non-editable install cannot locate the repository's web/ folder).
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    CRANETWIN_WEB_DIR=/app/web \
    CRANETWIN_HOST=0.0.0.0 \
    CRANETWIN_PORT=8000 \
    CRANETWIN_DATABASE_URL=sqlite:////data/cranetwin.db

WORKDIR /app
# the service's extras (PostgreSQL, Redis live bus, PDF reports, web UI, uvloop) at the versions
# CI tested (constraints.txt); the code, then the web UI's static files
COPY pyproject.toml README.md constraints.txt ./
COPY src ./src
RUN pip install -c constraints.txt '.[postgres,redis,reports,web,ingest]' \
    && useradd --create-home --uid 10001 cranetwin && mkdir -p /data && chown cranetwin /data
COPY web ./web

USER cranetwin
VOLUME ["/data"]
EXPOSE 8000 5005/udp

HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
  CMD python -c "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2).status == 200 else 1)"

CMD ["cranetwin", "serve"]
