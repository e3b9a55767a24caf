# One image for the API and the workers (docker-compose.yml picks the command).
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY kernels kernels
COPY worker worker
COPY service service
COPY scenes scenes
# Editable install: the package finds scenes/ and kernels/*.cl next to its code.
RUN pip install --no-cache-dir -e .
# The service runs as a user of its own: the code stays root's (read-only to it), and only
# its home (PoCL's kernel cache) and the data directory are its to write.
RUN useradd --create-home --uid 10001 --user-group photonfarm \
    && install --directory --owner photonfarm --group photonfarm --mode 0700 /data
USER photonfarm
ENV PYTHONUNBUFFERED=1 PYOPENCL_NO_CACHE=1 PHOTONFARM_DATA=/data
EXPOSE 8000
# 0.0.0.0 in the container: `photonfarm serve` refuses it without PHOTONFARM_TOKEN (or _FILE).
CMD ["photonfarm", "serve", "--host", "0.0.0.0", "--port", "8000", "--workers", "0"]
