"""How a process of the package starts, runs and ends, apart from what it does.

``signals``: the stop signals of a node process, working from its first import;
``stopping``: exiting at once and cleanly, and holding a stop during the imports;
``blas``: one BLAS thread per process unless set; ``rosidl_runtime``: ROS's message
packages without their code-generation half; ``warm``: a first start's compilation, paid
once where the package is installed (``python -m piezo_stage.process.warm``). The
nodes' executor and their ``main`` are ``nodes/_executor.py``: it builds nodes.
"""
