"""Operations and measurement tools, run from a checkout and never deployed: load tests
(loadtest), the memory soak (soak) and the crash-under-load test (crashtest) of a running
service, clients that speak HTTP through the SDK (ds3d_service.client); the speed against the
peer (peer_speed), the GPU check (gpu_check, gpu_profile) and the README's picture (bvh_strip).
Of the library the service's clients import only the provenance their reports record
(ds3d.util.provenance)."""
