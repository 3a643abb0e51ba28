# One image for every dammrl service; compose.yaml picks the command per container.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY dammrl ./dammrl
COPY schemas ./schemas
COPY services ./services
RUN pip install .

# Zenoh listens here when a service is given DAMMRL_BUS_LISTEN
EXPOSE 7447
CMD ["python", "-m", "services.sim", "--help"]
