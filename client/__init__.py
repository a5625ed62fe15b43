"""Python client library, CLI tools and the browser page (streaming-service issue)."""
