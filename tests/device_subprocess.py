"""Run a test script in a subprocess with forced host devices (JAX reads the device count
once, at start-up, so it cannot change inside the test process)."""
import json
import os
import subprocess
import sys


def run_on_devices(script: str, devices: int = 4, timeout: float = 300) -> dict:
    """Run ``script`` with ``devices`` forced CPU devices; return the JSON object it prints on
    its last line of standard output."""
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])
