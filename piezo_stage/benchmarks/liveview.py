"""`piezo-stage bench liveview`: the lockstep loop without and with the live view and
a client watching joint_states, alternated in pairs."""

from __future__ import annotations

from piezo_stage.benchmarks.loop import loop_run
from piezo_stage.benchmarks.procs import progress_runs


def watched_loop_run(env, steps, port):
    """A lockstep run with the live view and a client watching joint_states: the run's
    figures, and (messages received, their rate per wall-clock second)."""
    import threading

    from piezo_stage.benchmarks.foxglove_probe import connect, receive
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



def bench_liveview(steps=6000, pairs=3):
    """The lockstep loop with and without the live view and a watching client,
    alternated in the same invocation (the host's load drifts): the slowdown, and
    what the client receives."""
    import os
    import random
    import socket
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    print(f"bench liveview: lockstep loop ({steps} steps, recorder on) without and with "
          "the live view (Foxglove WebSocket) and a client watching joint_states, "
          f"alternated, {pairs} pairs")
    plain, watched, rates = [], [], []
    for k in progress_runs(range(pairs), "bench liveview: pairs"):
        res, err = loop_run(env, steps)
        if res is None:
            print("  the loop run failed:\n" + err)
            return 1
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        res_w, err, n, rate = watched_loop_run(env, steps, port)
        if res_w is None:
            print("  the watched loop run failed:\n" + err)
            return 1
        plain.append(res[0])
        watched.append(res_w[0])
        rates.append(rate)
        if n == 0:
            print(f"  pair {k + 1}: the client received nothing ({err or 'no error'})")
        if sum(res_w[3].values()):
            print(f"  pair {k + 1}: messages lost in the watched run: {res_w[3]}")
        print(f"  pair {k + 1}: without {res[0]} steps/s, with {res_w[0]} steps/s "
              f"(ratio {res_w[0] / res[0]:.2f}); the client got {n} joint_states, "
              f"{rate:.0f}/s; lost in the bag {sum(res_w[3].values())}")
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    slow = 1 - med(watched) / med(plain)
    print(f"  median: without {med(plain)} steps/s, with {med(watched)} steps/s: the loop "
          f"is {100 * slow:.1f} % slower; the client receives {med(rates):.0f} "
          "joint_states/s (max_rate_hz 200)")
    print(f"  target >= 100 joint_states/s to the client: "
          f"{'met' if med(rates) >= 100 else 'NOT met'}; loop slowed <= 10 %: "
          f"{'met' if slow <= 0.10 else 'NOT met'}")
    return 0
