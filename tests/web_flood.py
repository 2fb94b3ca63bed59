"""Abort latency under a flood of bad logins (docs/decisions/0058): python tests/web_flood.py REPO [N]: serves REPO's console on a seeded archive."""
import collections, concurrent.futures as cf, os, subprocess, sys, tempfile, time
from pathlib import Path
import requests
repo = Path(sys.argv[1]); n = int(sys.argv[2]) if len(sys.argv) > 2 else 100
sys.path[:0] = [str(repo), str(repo / "tests")]
from webutil import seed_trend_archive, free_port
from cell.web.users import UserStore
tmp = Path(tempfile.mkdtemp(prefix="flood-")); arch = tmp / "archive"; (tmp / "programs").mkdir()
ids = seed_trend_archive(arch, n_parts=3)
UserStore(arch / "console.sqlite").add("olga", "operator", "operator-pw-7q")
port = free_port(); url = f"http://127.0.0.1:{port}"
env = dict(os.environ, PYTHONPATH=str(repo), OMP_NUM_THREADS="1")
srv = subprocess.Popen([sys.executable, "-m", "cell.cli", "serve", "--port", str(port), "--archive", str(arch),
                        "--programs", str(tmp / "programs")], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
try:
    for _ in range(300):
        try: requests.get(url + "/login", timeout=1); break
        except requests.RequestException: time.sleep(0.2)
    tok = requests.post(url + "/api/token", json={"username": "olga", "password": "operator-pw-7q"}).json()["token"]
    h = {"Authorization": f"Bearer {tok}"}
    def bad(k):
        return requests.post(url + "/api/token", json={"username": f"u{k}", "password": "guess"},
                             headers={"X-Forwarded-For": f"10.0.{k // 250}.{k % 250}"}, timeout=600).status_code
    t0 = time.monotonic()
    with cf.ThreadPoolExecutor(max(n, 1)) as ex:
        fut = [ex.submit(bad, k) for k in range(n)]
        time.sleep(0.5)
        tg = time.monotonic()
        g = requests.get(url + f"/api/jobs/{ids[0]}", headers=h, timeout=600)
        get_s = time.monotonic() - tg
        ta = time.monotonic()
        r = requests.post(url + f"/api/jobs/{ids[0]}/abort", headers=h, timeout=600)
        abort_s = time.monotonic() - ta
        codes = collections.Counter(f.result() for f in fut)
    print(f"GET /api/jobs/ID answered {g.status_code} in {get_s:.2f} s; abort answered {r.status_code} in {abort_s:.2f} s during {n} bad logins; logins {dict(codes)} "
          f"in {time.monotonic() - t0:.1f} s")
finally:
    srv.terminate(); srv.wait(30)
