"""A cluster that lets no one in: scheduler, workers and ``btf run`` over mutual TLS.

Certificates are made for the test (trustme: a CA of its own, one certificate for the
scheduler and workers, one for the client); everything listens on 127.0.0.1 and is stopped.
"""

from __future__ import annotations

import pytest

from helpers import btf_process, dask_cluster

CONFIG = "stages:\n  - generate: {out: %s, material: wood, size: 32, sampling: 'abtf:4,2'}\n"

pytestmark = pytest.mark.distributed


@pytest.fixture(scope="module")
def tls_cluster(tmp_path_factory):
    import trustme

    folder = tmp_path_factory.mktemp("tls")
    ca = trustme.CA()
    ca.cert_pem.write_to_path(str(folder / "ca.pem"))
    ca.issue_cert("127.0.0.1", "localhost").private_key_and_cert_chain_pem.write_to_path(
        str(folder / "node.pem"))
    ca.issue_cert("btf-client").private_key_and_cert_chain_pem.write_to_path(
        str(folder / "client.pem"))
    other = trustme.CA()  # a CA the cluster does not trust
    other.issue_cert("intruder").private_key_and_cert_chain_pem.write_to_path(
        str(folder / "intruder.pem"))
    other.cert_pem.write_to_path(str(folder / "other-ca.pem"))
    tls = ("--tls-ca-file", str(folder / "ca.pem"), "--tls-cert", str(folder / "node.pem"))
    from distributed.security import Security

    security = Security(tls_ca_file=str(folder / "ca.pem"),
                        tls_client_cert=str(folder / "client.pem"), require_encryption=True)
    with dask_cluster(folder, protocol="tls", tls=tls, security=security) as (address, _):
        yield address, folder




@pytest.mark.slow  # 10 s, two runs on the cluster (every test here is in the slow set)
def test_btf_run_over_tls_with_certificates_from_flags_or_dask_config(tls_cluster, tmp_path):
    address, folder = tls_cluster
    config = tmp_path / "run.yaml"
    config.write_text(CONFIG % (tmp_path / "a.zarr"))
    done = btf_process("run", config, "--scheduler", address, "--tls-ca-file", folder / "ca.pem",
                       "--tls-cert", folder / "client.pem", "--quiet")
    assert done.returncode == 0, done.stderr
    config.write_text(CONFIG % (tmp_path / "b.zarr"))
    env = {"DASK_DISTRIBUTED__COMM__TLS__CA_FILE": str(folder / "ca.pem"),
           "DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT": str(folder / "client.pem")}
    done = btf_process("run", config, "--scheduler", address, "--quiet", env=env)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "a.zarr" / "zarr.json").is_file()
    assert (tmp_path / "b.zarr" / "zarr.json").is_file()


@pytest.mark.slow  # 9 s (a TLS cluster): kept out of the default run (4 min), run by .ci/run
def test_a_client_without_the_cluster_s_certificates_is_refused(tls_cluster, tmp_path):
    address, folder = tls_cluster
    config = tmp_path / "run.yaml"
    config.write_text(CONFIG % (tmp_path / "c.zarr"))
    missing = btf_process("run", config, "--scheduler", address, "--quiet")
    assert missing.returncode == 1 and "needs --tls-ca-file and --tls-cert" in missing.stderr
    intruder = btf_process("run", config, "--scheduler", address, "--tls-ca-file",
                           folder / "other-ca.pem", "--tls-cert", folder / "intruder.pem",
                           "--quiet")
    assert intruder.returncode == 1 and "cannot reach the dask scheduler" in intruder.stderr
    plain = btf_process("run", config, "--scheduler", address.replace("tls://", "tcp://"),
                        "--quiet")
    assert plain.returncode == 1
    assert not (tmp_path / "c.zarr").exists()
