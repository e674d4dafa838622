"""Names vulture takes for dead that are used from outside Python's sight (``tests/test_layout.py`` runs
vulture with this file): each line says who uses it."""
from vulture.whitelist_utils import Whitelist

_ = Whitelist()

# python-can calls these on every interface (BusABC): hil/bus/link.py, hil/bus/localbus.py
_.channel_info
_._recv_internal
_._is_shutdown
_._detect_available_configs
# the lazy public API: Python calls module __getattr__ / __dir__; hil.__init__._API names replay_log by string
_.__getattr__
_.__dir__
_.replay_log
# numba's @intrinsic signatures take (typingctx, ...) and codegen (context, builder, ...): identifier/kernels.py
_.typingctx
_.context
# FMI callbacks filled into a ctypes structure the FMU calls: plant/fmu_plant.py
_.logger
_.allocateMemory
_.freeMemory
_._callbacks
_.cat
_.inst
# only for annotations (TYPE_CHECKING): plant/fmu_plant.py
_.ModelDescription
# a reference kept so that CasADi's buffer outlives the compiled call bound to it: plant/model.py, reality.py
_._buffer
# mcap's Statistics record, written whole at the end of the file: hil/log/mcapfile.py
_.schema_count
_.channel_count
_.metadata_count
_.chunk_count
# Table 1 parameters read by name (getattr) as the load-transfer effect's defaults: plant/params.py
_.half_bogie_distance_m
_.half_wheelbase_m
_.coupler_height_m
_.bogie_height_m
# pytest hooks and marks
_.pytest_configure
_.pytest_report_header
_.pytest_terminal_summary
_.pytest_itemcollected
_.pytest_collection_modifyitems
_.pytestmark
# a fixture requested by name (tests/test_vcan.py), urllib's request target set by hand (tests/test_bus.py)
_.vcan0
_.selector
# pytest calls the plugin's hooks and an Item's runtest/reportinfo by name: hil/pytest_plugin.py
_.pytest_addoption
_.pytest_collect_file
_.pytest_collection_finish
_.pytest_sessionfinish
_.pytest_runtest_makereport
_.runtest
_.reportinfo
# pytest reads a test module's pytest_plugins, and runs autouse fixtures by themselves: tests/test_pytest_plugin.py
_.pytest_plugins
_._loaded
