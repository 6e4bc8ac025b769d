def pytest_configure(config):
    config.addinivalue_line("markers", "container: needs a Docker engine (deselect with -m 'not container')")
