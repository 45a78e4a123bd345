"""One node set per namespace: before a launch starts any node, it looks on its domain
for a set already running in its namespace. Two sets on one namespace would share
topics: the running set would take the newcomer's trajectory and its bag would hold
both sets' commands.

The look is a short-lived outside node: the graph's node names in the namespace (what
`ros2 node list` shows), and, to say whose set it is, the driver's latched ``state``,
whose values name the host and the launcher's pid."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

STATE_WAIT_S = 10.0  # for a running set's driver to say whose it is
BUSY_WAIT_S = 6.0    # for its node names, when the domain shows other nodes


def running_set(namespace: str, domain_id: int, wait_s: float = 2.0,
                cancel: threading.Event | None = None, report=None) -> str | None:
    """None when nothing runs in ``namespace`` on ``domain_id``; else who runs there
    ("host, pid N", or the node names when no driver announced itself). Up to
    ``wait_s`` for the graph to show the namespace's nodes (``BUSY_WAIT_S`` when it
    shows other nodes, whose discovery is going on): on a loaded host their names took
    longer than 0.5 s to arrive, and after ten outside nodes joined and left, over
    2 s; a shorter wait let a second launch go ahead beside a running set. A
    clean start pays the whole wait once (on a lab's busy domain up to 6 s): ``Look``
    spends it beside the start-up. ``cancel`` set: it ends within 50 ms, with None.
    ``report``: called with the answer before the look's node is torn down (its
    participant leaves the graph properly, a little after the answer is out)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from piezo_stage.nodes._common import QOS_EVENTS
    ns = "/" + namespace.strip("/")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(domain_id),
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("launch_check", context=ctx, start_parameter_services=False,
                             enable_rosout=False)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    who: dict[str, str] = {}

    def on_state(m: DiagnosticArray) -> None:
        who.update({kv.key: kv.value for kv in m.status[0].values} if m.status else {})
    node.create_subscription(DiagnosticArray, f"{ns}/state", on_state, QOS_EVENTS)

    def answer() -> str | None:
        t0 = time.monotonic()
        names: list = []
        limit = wait_s
        while not names:
            if cancel is not None and cancel.is_set():
                return None
            # (up to the wait's end, not past it: the answer is in within milliseconds)
            left = limit - (time.monotonic() - t0)
            ex.spin_once(timeout_sec=min(0.05, max(left, 0.001)))
            seen = [(n, s) for n, s in node.get_node_names_and_namespaces()
                    if (n, s) != ("launch_check", "/")]
            names = sorted(n for n, s in seen if s == ns)
            # a graph with other nodes in it is being discovered: give ours longer
            # (right after many nodes joined and left, the set's names came late)
            limit = BUSY_WAIT_S if seen else wait_s
            if time.monotonic() - t0 >= limit:
                break
        if not names:
            return None
        # its driver's latched state, if it has one: on a loaded host, with other nodes
        # just gone, it can take seconds to arrive, and a refusal sooner names only the
        # nodes seen by then
        end = time.monotonic() + STATE_WAIT_S
        while time.monotonic() < end and "host" not in who:
            if cancel is not None and cancel.is_set():
                return None
            ex.spin_once(timeout_sec=0.05)
        if "host" in who:
            return f"{who['host']}, pid {who.get('pid', '?')}"
        names = sorted(n for n, s in node.get_node_names_and_namespaces() if s == ns)
        return "nodes " + ", ".join(names)
    try:
        found = answer()
        if report is not None and not (cancel is not None and cancel.is_set()):
            report(found)
        return found
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


# the look's process: after its answer, what its middleware's teardown may take before
# it is killed [s] (10-100 ms when nothing hangs; see Look)
LOOK_TEARDOWN_S = 1.5
# and before its answer, beyond its own waits [s]: interpreter, imports, participant
LOOK_START_S = 30.0
# set (to anything): the look's process hangs after its answer, as it does when Fast
# DDS deadlocks in its teardown (the suite checks that the launcher goes on)
HANG_ENV = "PIEZO_STAGE_LOOK_HANGS"


class Look:
    """``running_set`` in a process of its own, begun as soon as the namespace and the
    domain are known: its wait (2 s on a clean start) then runs while the command
    imports and reads its config, and while the nodes import, instead of after them
    (launch to armed, `bench startup`). ``result()`` waits for the answer (raising an
    error the look met), which is in before the look's node is torn down; ``close()``
    waits for that teardown, ``LOOK_TEARDOWN_S`` at most, and kills the process after
    it; ``cancel()`` ends a look whose answer is no longer wanted (a config refused, a
    stop while starting) the same way, with nothing left behind.

    A process, not a thread: Fast DDS (2.14, Jazzy's) can deadlock while it destroys a
    participant that is discovering another one's endpoints: its teardown waits, in a
    spin, for a discovery callback that waits for a lock the teardown holds
    (DomainParticipantImpl::set_listener; Fast-DDS issue 6513 is its spin). rclpy holds
    the GIL through that call, so a look torn down in the launcher's thread while a set
    that had just ended left the domain froze the launcher for good, at a whole CPU,
    before it had started a node. The set's own nodes join only once the look's
    participant is gone (``close()`` before the start gate opens). The look's process
    keeps off shared memory (the real-time set's transport), so a kill leaves no port
    file behind; it dies with its parent."""

    def __init__(self, namespace: str, domain_id: int, wait_s: float = 2.0) -> None:
        import os
        import subprocess
        import sys
        import tempfile

        from piezo_stage.launcher.transport import realtime_transport_env
        self.namespace, self.domain_id, self.wait_s = namespace, int(domain_id), wait_s
        self._cancel = threading.Event()
        self._answered = threading.Event()
        self._answer: tuple[str | None, BaseException | None] = (None, None)
        env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain_id))
        env.update(realtime_transport_env(env))
        self._err = tempfile.TemporaryFile()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "piezo_stage.launcher.running", namespace,
             str(self.domain_id), repr(float(wait_s))], env=env, stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self._err, start_new_session=True)
        self._thread = threading.Thread(target=self._look, name="running-set look",
                                        daemon=True)
        self._thread.start()

    def _look(self) -> None:
        """The answer from the look's process, then its teardown, bounded."""
        import json
        import subprocess
        bound = threading.Timer(LOOK_START_S + self.wait_s + BUSY_WAIT_S + STATE_WAIT_S,
                                self._proc.kill)
        bound.daemon = True
        bound.start()
        try:
            assert self._proc.stdout is not None
            line = self._proc.stdout.readline()
        finally:
            bound.cancel()
        try:
            said = json.loads(line) if line.strip() else {}
        except ValueError:
            said = {}
        if "who" in said:
            self._answer = (said["who"], None)
        elif not self._cancel.is_set():
            self._answer = (None, RuntimeError(self._no_answer(said)))
        self._answered.set()
        try:
            self._proc.wait(LOOK_TEARDOWN_S)
        except subprocess.TimeoutExpired:  # its middleware's teardown hangs (above)
            self._proc.kill()
            self._proc.wait()

    def _no_answer(self, said: dict) -> str:
        if "error" in said:
            return f"the look for a set running in {self.namespace}: {said['error']}"
        try:
            code = self._proc.wait(LOOK_TEARDOWN_S)
        except Exception:  # noqa: BLE001 - still running: killed below
            code = None
        self._err.seek(0)
        last = [x for x in self._err.read().decode(errors="replace").splitlines()
                if x.strip()][-1:]
        return (f"the look for a set running in {self.namespace} ended without an answer"
                f" (exit {code})" + (f": {last[0].strip()}" if last else ""))

    def done(self) -> bool:
        return self._answered.is_set()

    def wait(self, timeout: float) -> bool:
        """Up to ``timeout`` seconds for the answer: whether it is in."""
        return self._answered.wait(timeout)

    def result(self) -> str | None:
        """None: nothing runs in the namespace; else who runs there."""
        self._answered.wait()
        who, error = self._answer
        if error is not None:
            raise error
        return who

    def close(self) -> None:
        """Wait for the look's process to end (its teardown, ``LOOK_TEARDOWN_S`` at
        most after its answer, then it is killed)."""
        self._thread.join()
        self._err.close()

    def cancel(self) -> None:
        """The answer is no longer wanted: the look's process ends within 50 ms and
        tears down (killed after ``LOOK_TEARDOWN_S``)."""
        self._cancel.set()
        if self._proc.stdin is not None:
            try:
                self._proc.stdin.close()  # its end of input: it stops looking
            except OSError:
                pass
        self._thread.join(LOOK_TEARDOWN_S + 0.5)
        if self._thread.is_alive():  # not even an answer yet, and not ending
            self._proc.kill()
        self.close()
        self._answered.set()


def main(argv: list[str] | None = None) -> int:
    """The look's process (``Look``): ``NAMESPACE DOMAIN WAIT_S``; one JSON line on
    stdout, ``{"who": ...}`` or ``{"error": ...}``, before its node is torn down. The
    end of its input cancels it."""
    import json
    import os
    import signal
    import sys
    args = sys.argv[1:] if argv is None else argv
    namespace, domain, wait_s = args[0], int(args[1]), float(args[2])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # its parent says when it ends
    try:
        import ctypes
        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    cancel = threading.Event()

    def until_input_ends() -> None:
        while os.read(0, 4096):  # the raw descriptor: no buffer's lock at exit
            pass
        cancel.set()
    threading.Thread(target=until_input_ends, daemon=True).start()

    def report(who: str | None) -> None:
        sys.stdout.write(json.dumps({"who": who}) + "\n")
        sys.stdout.flush()
        if os.environ.get(HANG_ENV):  # the suite's stand-in for the deadlock (Look)
            threading.Event().wait()
    try:
        running_set(namespace, domain, wait_s, cancel=cancel, report=report)
    except Exception as e:  # noqa: BLE001 - said to the parent, in one line
        sys.stdout.write(json.dumps({"error": f"{type(e).__name__}: {e}"}) + "\n")
        sys.stdout.flush()
        return 1
    return 0


@contextmanager
def begin_look(namespace: str, env=None):
    """A ``Look`` for ``namespace`` on the domain ``env`` (default os.environ) names, for
    a command to hand to its ``Launch`` (None where the domain is no number); cancelled
    on leaving (a no-op once answered)."""
    import os
    env = os.environ if env is None else env
    try:
        domain = int(env.get("ROS_DOMAIN_ID") or 0)
    except ValueError:  # not a domain: the launch says so where it looks itself
        yield None
        return
    look = Look(namespace, domain)
    try:
        yield look
    finally:
        look.cancel()


if __name__ == "__main__":
    import os
    import sys
    code = main()
    sys.stdout.flush()
    os._exit(code)  # torn down already; its input's reader still blocks in read()

