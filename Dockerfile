# The percept-memory app (CLI, web app and lookup workers), for docker-compose.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY percept_memory ./percept_memory
RUN pip install --no-cache-dir .
# MongoDB comes from MONGODB_URI (the compose file's replica set), not the embedded server.
EXPOSE 8000
# Beyond loopback, writes need PMEM_TOKEN; unset, a token is made up and printed at each start.
CMD ["pmem", "serve", "--host", "0.0.0.0", "--port", "8000"]
