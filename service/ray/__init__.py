"""Scale-out over a Ray cluster: joining one (`cluster`, without the web app), the service as a
Ray Serve application (`serve`), and the middleware of Ray's HTTP proxy (`proxy`)."""
