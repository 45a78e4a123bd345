"""`piezo-stage bench liveview`: the lockstep loop without and with the live view and
a client watching joint_states, alternated in pairs."""

from __future__ import annotations

from benchmarks.loop import loop_run
from benchmarks.procs import progress_runs


def watched_loop_run(env, steps, port):
    """A lockstep run with the live view and a client watching joint_states: the run's
    figures, and (messages received, their rate per wall-clock second)."""
    import threading

    from benchmarks.foxglove_probe import connect, receive
    done, got = threading.Event(), {}

    def watch():
        try:
            with connect(port, timeout_s=120) as ws:
                got["data"] = receive(ws, "/stage/joint_states", timeout_s=600,
                                      stop=done.is_set)[1]
        except Exception as e:  # noqa: BLE001 - reported with the run's figures
            got["error"] = f"client: {type(e).__name__}: {e}"
    client = threading.Thread(target=watch, daemon=True)
    client.start()
    res, err = loop_run(env, steps, foxglove_port=port)
    done.set()
    client.join(10)
    data = got.get("data", [])
    err = err or got.get("error")
    span = data[-1][2] - data[0][2] if len(data) > 1 else 0.0
    return res, err, len(data), (len(data) - 1) / span if span > 0 else 0.0



def bench_liveview(rep, steps=6000, pairs=3):
    """The lockstep loop with and without the live view and a watching client,
    alternated in the same invocation (the host's load drifts): the slowdown, and
    what the client receives (``rep``: the report)."""
    import os
    import random
    import socket
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    rep.title(f"the lockstep loop ({steps} steps, recorder on) without and with the live "
              "view (Foxglove WebSocket) and a client watching joint_states, alternated, "
              f"{pairs} pairs")
    plain, watched, rates, rows = [], [], [], []
    for k in progress_runs(range(pairs), "bench liveview: pairs"):
        res, err = loop_run(env, steps)
        if res is None:
            rep.fail("the loop run failed:\n" + err)
            return 1
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        res_w, err, n, rate = watched_loop_run(env, steps, port)
        if res_w is None:
            rep.fail("the watched loop run failed:\n" + err)
            return 1
        plain.append(res[0])
        watched.append(res_w[0])
        rates.append(rate)
        rows.append((k + 1, f"{res[0]} steps/s", f"{res_w[0]} steps/s",
                     f"{res_w[0] / res[0]:.2f}", f"{n} ({rate:.0f}/s)" if n else
                     f"nothing ({err or 'no error'})", sum(res_w[3].values())))
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    slow = 1 - med(watched) / med(plain)
    rows.append(("median", f"{med(plain)} steps/s", f"{med(watched)} steps/s",
                 f"{1 - slow:.2f}", f"{med(rates):.0f}/s", ""))
    rep.table(("pair", "without", "with", "ratio", "joint_states to the client",
               "lost in the bag"), rows, "the live view's max_rate_hz 200")
    rep.target(">= 100 joint_states/s to the client", med(rates) >= 100)
    rep.target("the loop slowed <= 10 %", slow <= 0.10)
    return 0
