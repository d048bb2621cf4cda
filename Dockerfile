# CWRR lab station: server + dashboard on the simulated plant (or a rig).
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 CWRR_DATA_DIR=/data NUMBA_CACHE_DIR=/tmp/numba
RUN useradd --create-home --uid 10001 cwrr && mkdir -p /data && chown cwrr /data
WORKDIR /opt/cwrr
COPY pyproject.toml README.md constraints.txt ./
COPY app ./app
# the versions the test suite passed with, not whatever is newest the day the image is built
RUN pip install --no-cache-dir -c constraints.txt .
USER cwrr
# compile the numba kernels into the image (NUMBA_CACHE_DIR): a container answers its health check
# in seconds instead of after a minute of compiling
RUN python -m app.engine.warm
VOLUME ["/data"]
EXPOSE 8000 8080
HEALTHCHECK --interval=15s --timeout=3s CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/api/health').status==200 else 1)"
CMD ["cwrr", "serve", "--host", "0.0.0.0", "--port", "8000", "--viser-port", "8080"]
