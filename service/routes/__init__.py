"""HTTP routers: `/disparity`, `/health*`, `/metrics`."""
