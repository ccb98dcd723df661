# One image for the dask scheduler, the workers and the runner (docker-compose.yml).
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY pipeline ./pipeline
COPY tasks ./tasks
COPY benchmarks ./benchmarks
COPY configs ./configs
RUN pip install --no-cache-dir .
# Outputs go to the shared volume; every container sees it at the same path, because tasks
# carry absolute paths to the stores they read and write.
WORKDIR /data
