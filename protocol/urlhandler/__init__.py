"""pyserial URL handlers of the protocol package.

Registered by appending ``"protocol.urlhandler"`` to
``serial.protocol_handler_packages`` (``protocol.transport.register_url_handlers``
does it), after which ``serial.serial_for_url("mem://NAME?end=a")`` opens an end
of an in-memory line (``protocol_mem``).
"""
