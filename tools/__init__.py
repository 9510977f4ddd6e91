"""Operations tools for a running ds3d service, run from a checkout and never deployed: load
tests (loadtest), the memory soak (soak) and the crash-under-load test (crashtest). Clients
only: they speak HTTP through the SDK (ds3d_service.client) and import nothing of the library."""
