# imunoise live service: `imunoise serve` with its API and dashboard on port 8000.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1

WORKDIR /app
COPY pyproject.toml README.md ./
COPY core ./core
COPY analysis ./analysis
COPY daq ./daq
COPY live ./live
COPY fleet ./fleet
COPY web ./web
COPY imunoise ./imunoise
RUN pip install . \
    && useradd --system --create-home --groups dialout imunoise \
    && mkdir -p /data && chown imunoise /data

USER imunoise
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/health', timeout=4).status != 200)"]

# Inside the container the API must listen beyond loopback, so a token is required
# (IMUNOISE_TOKEN); publish the port on the host's loopback unless you mean otherwise.
ENTRYPOINT ["imunoise"]
CMD ["serve", "--device", "sim:adis16350", "--host", "0.0.0.0", "--port", "8000", "--out", "/data"]
