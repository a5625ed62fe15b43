"""Training jobs (docs/jobs.md): the store, the worker, the training process
(``python -m server.jobs.run``, which imports no FastAPI) and ``service.JobService`` (store +
worker, started and stopped in the app's lifespan); the REST routes are server/routers/jobs.py.
"""
