"""Many runs (scene x views x method x options x seed) as one durable, resumable sweep, locally or on Ray.

``grid``: what to run (YAML grid -> run specs); ``runner``: one run (training + the one evaluator, in child
processes); ``store``: the results file every finished run appends to; ``report``: tables and plots from
the records; ``cli``: the ``frugalnerf-sweep`` command, which schedules the runs as Ray tasks; ``gate``:
``frugalnerf-gate``, the quality gate, a sweep of the gate's scenes compared with their recorded baseline.
"""
