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
ENV PYTHONUNBUFFERED=1 PYOPENCL_NO_CACHE=1
EXPOSE 8000
CMD ["photonfarm", "serve", "--host", "0.0.0.0", "--port", "8000", "--workers", "0"]
