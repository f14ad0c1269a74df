# The percept-memory app (CLI, later the web app and the workers), for docker-compose.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY percept_memory ./percept_memory
RUN pip install --no-cache-dir .
# MongoDB comes from MONGODB_URI (the compose file's replica set), not the embedded server.
CMD ["pmem", "info"]
