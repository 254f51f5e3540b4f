# The posefuse estimator (also used for the replaying camera client in docker-compose.yml).
FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
# the root of the repository is the package posefuse (__init__.py), its folders the subpackages
COPY pyproject.toml README.md __init__.py ./
COPY estimator estimator
COPY sim sim
COPY service service
COPY clients clients
COPY bench bench
COPY cli cli
COPY catalogs catalogs
COPY models models
COPY recordings recordings
# a regular install, as a wheel: the catalog, models and recordings go with it as package data
RUN pip install --no-cache-dir .
# the verification's and the front end's voting's compiled loops, built now into numba's cache
# beside them (not at start-up)
RUN python -c "from posefuse.estimator.verification.kernels import compile_kernels as c; c()" \
    && python -c "from posefuse.estimator.frontend.voting import compile_kernels as c; c()"
# template banks are built at start-up into this cache; mount a volume to keep them
ENV POSEFUSE_CACHE=/cache
# few malloc arenas: freed frame buffers go back to the system instead of staying per thread
ENV MALLOC_ARENA_MAX=2
# the HTTP API listens on all of the container's interfaces; docker-compose.yml publishes it on
# the host's loopback only (docs/security.md says how to expose it, with a token)
EXPOSE 8000
CMD ["posefuse", "serve", "--mode", "client", "--connect", "tcp/router:7447", "--http-host", "0.0.0.0"]
