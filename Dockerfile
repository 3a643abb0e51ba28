# One image for every dammrl service; compose.yaml picks the command per container.
# docs/containers.md: build arguments, image size, the choices made here.
#
#   docker build -t dammrl:latest .                         # CPU-only torch (default)
#   docker build --build-arg PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cu128 \
#                -t dammrl:cuda .                             # a CUDA build of torch

# ---- requirements: the dependencies of pyproject.toml, as a requirements file ----------
# Its own stage: the install below is rebuilt only when this list changes, not when
# anything else in pyproject.toml (tool settings, package data) does. With the `view`
# extra: `dammrl view` (Foxglove) runs in a container too, and every module imports.
FROM python:3.11-slim AS requirements
WORKDIR /src
COPY pyproject.toml ./
RUN python -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; print(*p['dependencies'], *p['optional-dependencies']['view'], sep='\n')" > requirements.txt

# ---- build: a virtual environment with dammrl and its dependencies -------------------
FROM python:3.11-slim AS build

# Where torch comes from. PyTorch's CPU index carries torch==X+cpu, which pip prefers to
# PyPI's X (a CUDA build, 5 GB more): PEP 440 sorts a local version after its public one.
# A CUDA index (.../whl/cu128) gives a CUDA image; a local wheel server works the same.
ARG PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu
# a plain-http index (e.g. a local wheel server) must be named trusted; unset by default
ARG PIP_TRUSTED_HOST
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1

RUN python -m venv /opt/dammrl
ENV PATH=/opt/dammrl/bin:$PATH
WORKDIR /src

# The dependencies first: a code change reuses this layer.
COPY --from=requirements /src/requirements.txt ./
RUN pip install -r requirements.txt
# Fail rather than ship CUDA by accident: an unreachable index only warns, and pip then
# takes PyPI's torch. A CUDA torch is accepted only from a CUDA index (.../cu*).
RUN python -c "import sys, torch; print('torch', torch.__version__); sys.exit(bool(torch.version.cuda) and '/cu' not in sys.argv[1])" "$PIP_EXTRA_INDEX_URL"

# Build-time only, never read by a running service (~340 MB): C/C++ headers, static
# libraries, torch's C++ test binaries.
RUN cd /opt/dammrl/lib/python3.11/site-packages \
 && rm -rf torch/include torch/test cmeel.prefix/include \
 && find . -name '*.a' -delete

# The package as a wheel, installed in the runtime stage: a code change rebuilds only that
# small layer, not the copy of the environment. The build context is .dockerignore's
# allow-list, whose package folders are pyproject.toml's own package patterns; the check
# stops the build, naming the file, if the wheel lacks anything of those folders.
COPY . ./
RUN pip wheel --no-deps --wheel-dir /wheels . \
 && python docker/check_image.py wheel /wheels/*.whl

# ---- runtime: the environment on a clean base, shared libraries, a non-root user -----
FROM python:3.11-slim

# HOME=/tmp: any user (compose sets the host's UID) has a writable home for caches
ENV PATH=/opt/dammrl/bin:$PATH PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 HOME=/tmp \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# libgomp1: the OpenMP runtime of pinocchio; nothing else was missing when the stack ran
RUN apt-get update \
 && apt-get install -y --no-install-recommends libgomp1 \
 && rm -rf /var/lib/apt/lists/*

COPY --from=build /opt/dammrl /opt/dammrl
COPY --from=build /wheels /tmp/wheels
RUN pip install --no-deps --no-cache-dir /tmp/wheels/*.whl && rm -rf /tmp/wheels
# Every module imports (shared libraries included), the URDF builds the scene, every
# shipped policy loads: else the build stops here with one line each, not a service later.
COPY --from=build /src/docker/check_image.py /tmp/check_image.py
# (its own HOME: the libraries' caches written on import must not land in the services' /tmp)
RUN HOME=/tmp/check-home python /tmp/check_image.py installed \
 && rm -rf /tmp/check-home /tmp/check_image.py

# The default user; compose runs the services as the host user instead (user: UID:GID),
# so recordings in ./sessions belong to whoever started the stack.
ARG UID=1000
ARG GID=1000
RUN groupadd --gid "$GID" dammrl \
 && useradd --uid "$UID" --gid "$GID" --no-create-home --home-dir /tmp dammrl

WORKDIR /
USER dammrl

# Zenoh listens here when a service is given DAMMRL_BUS_LISTEN
EXPOSE 7447
CMD ["python", "-m", "services.sim", "--help"]
