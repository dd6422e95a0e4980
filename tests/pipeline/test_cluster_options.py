"""Cluster and store edges of the command line: ``parse_storage_options``, the Slurm
directive flags (rendered job script, no Slurm needed) and the dashboard line."""

from __future__ import annotations

import json
import re
import urllib.request

import pytest

from mocapflow.pipeline.executors import ExecutorError, SlurmOptions, dashboard_link
from mocapflow.pipeline.store_backends import STORAGE_OPTIONS_ENV, parse_storage_options

SECRET = "hunter2-s3cr3t"

# ----------------------------------------------------------------- parse_storage_options


def test_storage_options_dotted_keys_and_yaml_values():
    opts = parse_storage_options([
        "client_kwargs.endpoint_url=http://127.0.0.1:9000",
        "client_kwargs.region_name=eu-west-1",
        "anon=false", "config_kwargs={retries: {max_attempts: 2}}",
        "default_block_size=1048576", "key='0123'", "token=", "profile = lab",
    ])
    assert opts == {
        "client_kwargs": {"endpoint_url": "http://127.0.0.1:9000", "region_name": "eu-west-1"},
        "anon": False, "config_kwargs": {"retries": {"max_attempts": 2}},
        "default_block_size": 1048576, "key": "0123", "token": None, "profile": "lab",
    }
    assert parse_storage_options(["a=1", "a=2"]) == {"a": 2}  # later items win
    assert parse_storage_options(["url=http://h/?x=1"]) == {"url": "http://h/?x=1"}
    assert parse_storage_options() == {} and parse_storage_options([], "  ") == {}


def test_storage_options_env_is_the_base_items_update_it():
    env = json.dumps({"key": "k", "secret": SECRET,
                      "client_kwargs": {"endpoint_url": "http://a", "region_name": "r"}})
    assert parse_storage_options([], env) == json.loads(env)
    assert parse_storage_options(["client_kwargs.endpoint_url=http://b", "anon=true"], env) == {
        "key": "k", "secret": SECRET, "anon": True,
        "client_kwargs": {"endpoint_url": "http://b", "region_name": "r"}}
    # a mapping item merges key by key too
    assert parse_storage_options(["client_kwargs={verify: false}"], env)["client_kwargs"] == {
        "endpoint_url": "http://a", "region_name": "r", "verify": False}
    # ... and a scalar replaces a mapping
    assert parse_storage_options(["client_kwargs=null"], env)["client_kwargs"] is None


@pytest.mark.parametrize(("items", "env", "named"), [
    ([f"secret{SECRET}"], None, f"'secret{SECRET}'"),  # no '=': the whole item is the key
    ([f"={SECRET}"], None, "''"),
    ([f"client_kwargs..x={SECRET}"], None, "client_kwargs..x"),
    ([f"secret={SECRET}", f"secret.x={SECRET}"], None, "secret.x"),
    ([f"a.b={SECRET}", f"a.b.c={SECRET}"], None, "a.b.c: a.b is not a mapping"),
    ([], f'{{"secret": "{SECRET}"', STORAGE_OPTIONS_ENV),
    ([], f'["{SECRET}"]', f"{STORAGE_OPTIONS_ENV} must be a JSON object"),
    ([f"secret=!!binary {SECRET}"], None, "--storage-option secret"),
])
def test_storage_options_bad_items_name_the_key_never_the_value(items, env, named):
    with pytest.raises(ValueError) as info:
        parse_storage_options(items, env)
    msg = str(info.value)
    assert named in msg and "\n" not in msg
    if named != f"'secret{SECRET}'":  # (an item without '=' is all key)
        assert SECRET not in msg


def test_storage_option_errors_on_the_command_line(cli, monkeypatch, tmp_path):
    code, out, err = cli("verify", "--store", "s3://bucket/x", "--storage-option",
                         f"secret={SECRET}", "--storage-option", "secret.sub=1")
    assert code == 2 and err.startswith("mocapflow: error: --storage-option secret.sub")
    assert SECRET not in err and len(err.splitlines()) == 1
    monkeypatch.setenv(STORAGE_OPTIONS_ENV, f'{{"secret": "{SECRET}",}}')
    code, out, err = cli("verify", "--store", "s3://bucket/x")
    assert code == 2 and STORAGE_OPTIONS_ENV in err and "not valid JSON" in err
    assert SECRET not in err and len(err.splitlines()) == 1
    # a local store ignores the environment's options (they are for URL stores)
    code, out, err = cli("verify", "--store", tmp_path / "s")
    assert code == 0, err


# ----------------------------------------------------------------- slurm


def test_slurm_flags_reach_the_job_script(cli, toy_config, tmp_path):
    logs = tmp_path / "slurm-logs"
    code, out, err = cli("run", toy_config, "--executor", "slurm", "--slurm-partition", "p",
                         "--slurm-account", "a", "--slurm-gres", "gpu:1",
                         "--slurm-walltime", "02:00:00", "--slurm-log-dir", logs,
                         "--slurm-job-extra=--constraint=avx2",
                         "--slurm-job-extra", "#SBATCH --exclusive", "--print-job-script")
    assert code == 0, err
    sbatch = [line for line in out.splitlines() if line.startswith("#SBATCH")]
    for want in ("#SBATCH -p p", "#SBATCH -A a", "#SBATCH -t 02:00:00", "#SBATCH --gres=gpu:1",
                 "#SBATCH --constraint=avx2", "#SBATCH --exclusive",
                 f"#SBATCH -e {logs}/mocapflow-%J.err", f"#SBATCH -o {logs}/mocapflow-%J.out"):
        assert want in sbatch, out
    assert logs.is_dir()  # made now: sbatch needs it, and jobs without it fail unseen
    code, out, err = cli("run", toy_config, "--executor", "slurm", "--print-job-script",
                         "--slurm-log-dir", tmp_path / "slurm logs")
    assert code == 2 and out == "" and len(err.splitlines()) == 1
    assert "--slurm-log-dir" in err and "spaces" in err and not (tmp_path / "slurm logs").exists()


def test_slurm_options_defaults_leave_directives_out():
    kw = SlurmOptions().cluster_kwargs()
    assert "queue" not in kw and "account" not in kw and "log_directory" not in kw
    assert "job_extra_directives" not in kw
    assert SlurmOptions(job_extra=[" #SBATCH  --qos=long "]).directives() == ["--qos=long"]


@pytest.mark.parametrize("bad", ["constraint=avx2", "", "#SBATCH", "--a\n#SBATCH --b"])
def test_bad_slurm_job_extra_is_one_line(cli, toy_config, bad):
    with pytest.raises(ExecutorError, match="--slurm-job-extra"):
        SlurmOptions(job_extra=[bad]).directives()
    code, out, err = cli("run", toy_config, "--executor", "slurm", f"--slurm-job-extra={bad}",
                         "--print-job-script")
    assert code != 0 and out == ""
    assert err.startswith("mocapflow: error: --slurm-job-extra") and len(err.splitlines()) == 1
    assert "Traceback" not in err


# ----------------------------------------------------------------- dashboard


def test_local_cluster_prints_the_dashboard_link(cli, toy_config, tmp_path):
    code, out, err = cli("run", toy_config, "--store", tmp_path / "s", "--executor", "local",
                         "--workers", "1", "--target", "read")
    assert code == 0, err
    links = re.findall(r"^dashboard: (\S+)$", err, re.MULTILINE)
    assert len(links) == 1 and re.fullmatch(r"http://[^/]+:\d+/status", links[0]), err
    # -q: the cluster starts (the tasks are forced) but prints no dashboard line
    code, out, err = cli("run", toy_config, "--store", tmp_path / "s", "--executor", "local",
                         "--workers", "1", "--target", "read", "--force", "read", "-q",
                         "--json")
    assert code == 0 and json.loads(out)["counts"]["computed"] == 5
    assert "dashboard" not in err, err


def test_dashboard_link_none_without_a_dashboard():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster, \
            Client(cluster, set_as_default=False) as client:
        assert dashboard_link(client) is None
        assert client.dashboard_link  # (distributed names its metrics server's port)
    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster, \
            Client(cluster, set_as_default=False) as client:
        link = dashboard_link(client)
        assert link is not None and re.fullmatch(r"http://[^/]+:\d+/status", link)
        with urllib.request.build_opener(urllib.request.ProxyHandler({})).open(
                link, timeout=20) as page:
            assert page.status == 200 and b"bokeh" in page.read().lower()
