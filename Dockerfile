# One image for the dask scheduler, the workers and the runner (docker-compose.yml).
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY pipeline ./pipeline
COPY tasks ./tasks
COPY benchmarks ./benchmarks
COPY configs ./configs
RUN pip install --no-cache-dir .
# glibc: blocks of 16 MiB and more are mapped and unmapped on their own, so that the worker
# threads' arenas do not fragment (pipeline.session.steady_memory; BENCHMARKS.md, issue 27).
ENV MALLOC_MMAP_THRESHOLD_=16777216 MALLOC_TRIM_THRESHOLD_=8388608
# A worker that crashes in C code (a segfault) prints every thread's Python stack to its log
# first, so the log says where it died (issue 36: a worker once died so in libpython).
ENV PYTHONFAULTHANDLER=1
# Outputs go to the shared volume; every container sees it at the same path, because tasks
# carry absolute paths to the stores they read and write.
WORKDIR /data
