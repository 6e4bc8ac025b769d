"""The HTTP side of the service: the FastAPI app, its routes, schemas, errors, middleware and
metrics, the response bodies, and the request pipeline both disparity routes share."""
