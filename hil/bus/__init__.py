"""The bus: opening one by name, the local bus, the frame codec over hil/hil.dbc, frame authentication, verdicts."""
