"""HTTP routers: `/disparity`, `/health*`, `/models*`, `/metrics`, and the web page (`/`, `/static/*`)."""
