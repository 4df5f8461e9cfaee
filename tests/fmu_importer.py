"""An FMI master that knows nothing of regolith-cosim: it drives soil FMUs with fmpy or libcosim.

Run by tests/test_soil_fmu.py as `python -I -S fmu_importer.py JOB.json RESULT.json` with
only fmpy, libcosimpy and their dependencies on sys.path (job["sandbox"]); it checks that
regolith-cosim (cosim, soil) and Warp cannot be imported. Standard library + fmpy/libcosimpy only.

Job (JSON):
    sandbox     folder with fmpy, libcosimpy and their dependencies
    master      "fmpy" or "libcosim"
    instances   [{"fmu", "unzip", "name", "start": {variable: value}, "logging": bool}]
    steps       [{"h": step [s], "inputs": [{variable: value} per instance],
                  "before": null | "kill" | "stop" (SIGKILL / SIGSTOP the first instance's server)}]
                A discarded step is not counted: the next step starts at the same time.
                "save_state": true takes an FMU state before the step (fmi2GetFMUstate / fmi3GetFMUState);
                "restore_state": true restores it before the step (after a Discard: a master's retry).
                "reset": true resets every instance before the step (fmi2Reset / fmi3Reset) and sets it
                up again from its start values; the steps start over at t = 0.
                "t_offset": a step from t + t_offset instead of t (a master that goes on after a Discard).
    go_on_after_error   (optional) true: the steps go on after a step's Error (the master restores an
                FMU state, as FMI allows after an Error, sets right inputs and steps again); the default
                stops at the first Error
                An input the FMU refuses (setReal / setFloat64 Error) is listed in result["set_errors"]
                as [step index, variable] and the step is still taken.
    master "simulate": fmpy.simulate_fmu on the first instance's FMU with its start values until
                stop_time (output_interval h of the first step); the result holds its last time, or what
                it raised.
    locale      (optional) the host's locale: setlocale(LC_ALL, locale) before anything loads, as a C or
                Python host that honours its user's locale does ("" takes LC_ALL / LANG); the result's
                "decimal_point" is the C library's then
    pid_file    (optional) write the server pids here after initialization, then sleep
                `linger` seconds before stepping (for killing this importer from outside)
Result (JSON): status per step and instance ("ok", "discard", "error"), outputs per step and
instance (every output variable), elapsed [s] per step, log messages, server pids,
"regolith_importable" (must be false), and "refused" when libcosim cannot load an FMU.
"""

import json
import os
import signal
import sys
import time

job = json.load(open(sys.argv[1]))
sys.path.insert(0, job["sandbox"])

import importlib.util  # noqa: E402

REGOLITH_IMPORTABLE = {name: importlib.util.find_spec(name) is not None for name in ("cosim", "soil", "warp")}

messages = []
STATUS = {0: "ok", 1: "warning", 2: "discard", 3: "error", 4: "fatal"}


def children():
    """Pids of this process's child processes (the soil servers)."""
    me = str(os.getpid())
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[1] == me:
                found.append(int(entry))
    return sorted(found)


class FmpySoil:
    def __init__(self, spec):
        from fmpy import extract, read_model_description

        self.spec = spec

        self.md = read_model_description(spec["fmu"])
        self.variables = {v.name: v for v in self.md.modelVariables}
        unzip = extract(spec["fmu"], unzipdir=spec["unzip"])
        kwargs = dict(
            guid=self.md.guid,
            unzipDirectory=unzip,
            modelIdentifier=self.md.coSimulation.modelIdentifier,
            instanceName=spec["name"],
        )
        self.version = int(self.md.fmiVersion[0])
        if self.version == 2:
            from ctypes import byref

            from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE
            from fmpy.logging import addLoggerProxy

            self.fmu = FMU2Slave(**kwargs)
            callbacks = fmi2CallbackFunctions()
            callbacks.allocateMemory = defaultCallbacks.allocateMemory
            callbacks.freeMemory = defaultCallbacks.freeMemory
            callbacks.logger = fmi2CallbackLoggerTYPE(self._log2)
            addLoggerProxy(byref(callbacks))  # formats the FMI 2.0 printf-style messages
            self._callbacks = callbacks
            self.fmu.instantiate(callbacks=callbacks, loggingOn=spec.get("logging", False))
            self.fmu.setupExperiment(startTime=0.0)
            self.fmu.enterInitializationMode()
        else:
            from fmpy.fmi3 import FMU3Slave

            self.fmu = FMU3Slave(**kwargs)
            self.fmu.instantiate(loggingOn=spec.get("logging", False), logMessage=self._log3)
            self.fmu.enterInitializationMode(startTime=0.0)
        self.start_status = self.set(spec.get("start", {}))

    def _log2(self, env, name, status, category, message):
        messages.append([STATUS[status], category.decode(), message.decode()])
        print(f"[{STATUS[status]}] {message.decode()}")  # as fmpy's default logger does

    def _log3(self, env, status, category, message):
        messages.append([STATUS[status], category.decode(), message.decode()])
        print(f"[{STATUS[status]}] {message.decode()}")

    def set(self, values):
        """Set the values; 'ok', or the status of the first call the FMU refused."""
        for name, value in values.items():
            v = self.variables[name]
            if v.type == "String":
                setter = self.fmu.setString
            else:
                setter = self.fmu.setReal if self.version == 2 else self.fmu.setFloat64
            status = self._call(lambda setter=setter, v=v, value=value: setter([v.valueReference], [value]))
            if status != "ok":
                return status
        return "ok"

    def outputs(self):
        out = {}
        for name, v in self.variables.items():
            if v.causality == "output":
                if v.type in ("Real", "Float64"):
                    value = (self.fmu.getReal if self.version == 2 else self.fmu.getFloat64)([v.valueReference])[0]
                else:
                    value = (self.fmu.getInteger if self.version == 2 else self.fmu.getInt32)([v.valueReference])[0]
                out[name] = value
        return out

    def initialize(self):
        return self._call(self.fmu.exitInitializationMode)

    def reset(self):
        """fmi2Reset / fmi3Reset, then the instance set up again from its start values, as at the start."""
        if getattr(self, "state", None) is not None:
            self.free_state()
        self.fmu.reset()
        if self.version == 2:
            self.fmu.setupExperiment(startTime=0.0)
            self.fmu.enterInitializationMode()
        else:
            self.fmu.enterInitializationMode(startTime=0.0)
        self.set(self.spec.get("start", {}))
        return self.initialize()

    def step(self, t, h):
        return self._call(lambda: self.fmu.doStep(t, h))

    def _call(self, call):
        from fmpy.fmi1 import FMICallException

        try:
            call()
            return "ok"
        except FMICallException as error:
            return STATUS[int(error.status)]

    def save_state(self):
        if getattr(self, "state", None) is not None:
            self.free_state()
        self.state = self.fmu.getFMUstate() if self.version == 2 else self.fmu.getFMUState()

    def restore_state(self):
        (self.fmu.setFMUstate if self.version == 2 else self.fmu.setFMUState)(self.state)

    def free_state(self):
        (self.fmu.freeFMUstate if self.version == 2 else self.fmu.freeFMUState)(self.state)
        self.state = None

    def close(self):
        if getattr(self, "state", None) is not None:
            self.free_state()
        self.fmu.terminate()
        self.fmu.freeInstance()


class LibcosimSoils:
    """All instances in one libcosim execution (fixed step, override manipulator for the inputs)."""

    def __init__(self, specs, h):
        from libcosimpy._internal import get_last_error_message
        from libcosimpy.CosimExecution import CosimExecution
        from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
        from libcosimpy.CosimManipulator import CosimManipulator
        from libcosimpy.CosimObserver import CosimObserver
        from libcosimpy.CosimSlave import CosimLocalSlave

        log_output_level(CosimLogLevel.WARNING)  # libcosim prints everything to stdout by default
        step_ns = round(h * 1e9)
        if abs(step_ns * 1e-9 - h) > 1e-15 * h:
            raise ValueError("libcosim steps in whole nanoseconds")
        self.execution = CosimExecution.from_step_size(step_size=step_ns)
        self.observer = CosimObserver.create_last_value()
        self.execution.add_observer(self.observer)
        self.manipulator = CosimManipulator.create_override()
        self.execution.add_manipulator(self.manipulator)
        self.slaves, self.refs, self.outputs_of = [], [], []
        self._keep = []
        for spec in specs:
            slave = CosimLocalSlave(fmu_path=spec["fmu"], instance_name=spec["name"])
            if not slave.ptr():  # libcosimpy crashes on a slave it could not create
                raise RuntimeError(f"libcosim cannot load {spec['fmu']}: {get_last_error_message()}")
            self._keep.append(slave)
            index = self.execution.add_local_slave(slave)
            variables = self.execution.slave_variables(index)
            refs = {v.name.decode(): (v.reference, v.type) for v in variables}
            for name, value in spec.get("start", {}).items():
                self.execution.real_initial_value(index, refs[name][0], value)
            self.slaves.append(index)
            self.refs.append(refs)
            self.outputs_of.append([v.name.decode() for v in variables if v.causality == 2])

    def step(self, inputs):
        from libcosimpy._internal import get_last_error_message

        for index, refs, values in zip(self.slaves, self.refs, inputs):
            names = list(values)
            self.manipulator.slave_real_values(index, [refs[n][0] for n in names], [values[n] for n in names])
        ok = self.execution.step(1)
        if not ok:
            messages.append(["error", "libcosim", get_last_error_message()])
        return "ok" if ok else "error"

    def outputs(self):
        result = []
        for index, refs, names in zip(self.slaves, self.refs, self.outputs_of):
            reals = [n for n in names if refs[n][1] == 0]
            integers = [n for n in names if refs[n][1] == 1]
            out = dict(zip(reals, self.observer.last_real_values(index, [refs[n][0] for n in reals])))
            out.update(zip(integers, self.observer.last_integer_values(index, [refs[n][0] for n in integers])))
            result.append(out)
        return result


def run():
    if "locale" in job:
        import locale

        locale.setlocale(locale.LC_ALL, job["locale"])
    result = {
        "decimal_point": __import__("locale").localeconv()["decimal_point"],
        "regolith_importable": REGOLITH_IMPORTABLE,
        "status": [],
        "outputs": [],
        "elapsed": [],
        "messages": messages,
        "server_pids": [],
    }
    if job["master"] == "simulate":
        from fmpy import simulate_fmu

        spec = job["instances"][0]
        started = time.perf_counter()
        try:
            outcome = simulate_fmu(
                spec["fmu"],
                start_values=spec.get("start", {}),
                stop_time=job["stop_time"],
                output_interval=job["steps"][0]["h"],
            )
            result["last_time"] = float(outcome["time"][-1])
            result["servers_after_free"] = children()
        except Exception as error:  # fmpy gives up on an FMI 3.0 Discard with an exception
            result["raised"] = f"{type(error).__name__}: {error}"
        result["elapsed"].append(time.perf_counter() - started)
        return result
    if job["master"] == "libcosim":
        try:
            soils = LibcosimSoils(job["instances"], job["steps"][0]["h"])
        except RuntimeError as error:
            result["refused"] = str(error)
            return result
        for step in job["steps"]:
            started = time.perf_counter()
            status = soils.step(step["inputs"])
            result["elapsed"].append(time.perf_counter() - started)
            result["status"].append([status] * len(soils.slaves))
            result["outputs"].append(soils.outputs())
            if not result["server_pids"]:
                result["server_pids"] = children()
        soils.execution.stop()
        return result
    soils = [FmpySoil(spec) for spec in job["instances"]]
    result["status"].append([soil.initialize() for soil in soils])
    result["outputs"].append([soil.outputs() for soil in soils])
    result["server_pids"] = children()
    if job.get("pid_file"):
        with open(job["pid_file"], "w") as f:
            json.dump(result["server_pids"], f)
        time.sleep(job.get("linger", 0))
    t = 0.0
    result["set_errors"] = [[-1, "start values"] for soil in soils if soil.start_status != "ok"]
    for index, step in enumerate(job["steps"]):
        if step.get("before") in ("kill", "stop"):
            os.kill(result["server_pids"][0], signal.SIGKILL if step["before"] == "kill" else signal.SIGSTOP)
        if step.get("reset"):  # every instance reset and initialized again: the steps start over at 0
            result["reset_status"] = [soil.reset() for soil in soils]
            t = 0.0
        for soil, values in zip(soils, step["inputs"]):
            if step.get("restore_state"):
                soil.restore_state()
            if step.get("save_state"):
                soil.save_state()
            for name, value in values.items():
                if soil.set({name: value}) != "ok":
                    result["set_errors"].append([index, name])
        started = time.perf_counter()
        statuses = [soil.step(t + step.get("t_offset", 0.0), step["h"]) for soil in soils]
        result["elapsed"].append(time.perf_counter() - started)
        result["status"].append(statuses)
        result["outputs"].append([soil.outputs() for soil in soils])
        if all(s == "ok" for s in statuses):
            t += step["h"]
        if "error" in statuses and not job.get("go_on_after_error"):
            break
    for soil in soils:
        soil.close()
    result["servers_after_free"] = children()
    return result


if __name__ == "__main__":
    outcome = run()
    with open(sys.argv[2], "w") as f:
        json.dump(outcome, f)
