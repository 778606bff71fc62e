# One image for the API, the workers and the one-shot migration (docker-compose.yml).
FROM python:3.11-slim-bookworm
ENV PYTHONUNBUFFERED=1 UV_PROJECT_ENVIRONMENT=/opt/venv PATH=/opt/venv/bin:$PATH
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libegl1 libx11-6 libgomp1 curl \
 && rm -rf /var/lib/apt/lists/* \
 && pip install --no-cache-dir uv==0.13.9
WORKDIR /srv/twindelta
COPY pyproject.toml uv.lock README.md ./
RUN uv sync --frozen --no-dev --no-install-project
COPY app ./app
COPY workers ./workers
COPY migrations ./migrations
COPY alembic.ini ./
RUN uv sync --frozen --no-dev
# The process runs as uid 1000. A named volume mounted at /data takes this folder's owner on
# first use, so create it owned by that user (files, the SQLite file, the beat schedule).
RUN useradd --uid 1000 --user-group --no-create-home --home-dir /data twindelta \
 && mkdir -p /data \
 && chown 1000:1000 /data
USER 1000:1000
EXPOSE 8000
CMD ["uvicorn", "app.main:create_app", "--factory", "--host", "0.0.0.0", "--port", "8000"]
