"""spherejax_hw (the folder hw/): control of the integrating-sphere multispectral instrument over
pyserial, and emulated devices that follow the vendors' protocols (docs/instrument.md).

    errors        InstrumentError, the root of every hw/ error; HardwareError and its kinds:
                  DeviceTimeout, ProtocolError, DeviceError, PortError; AcquisitionError and
                  AcquisitionStopped
    serialline    the echo / value line / "> " prompt protocol both Thorlabs devices speak
    filterwheel   Thorlabs FW102C / FW212C filter wheel
    shutter       Thorlabs SC10 shutter controller
    filterbank    stacked wheels as one band selector (band -> wheel and slot from the profile)
    camera        the camera interface; simcamera (renders frames from spherejax's simulator),
                  pvcam (PyVCAM, imported lazily), genicam (GigE Vision / USB3 Vision cameras
                  through Aravis 0.8 and PyGObject, imported lazily)
    lamp          the xenon lamp as a manual device: lamp hours and warm-up in a state file
    profile       the instrument profile (TOML)
    emulators     FW102C / FW212C and SC10 state machines served on pseudo-terminals
    acquire       the acquisition protocol, resumable, into a session: `acquire`, one run start
                  to finish, over acquisition_devices (connect and check the devices),
                  acquisition_protocol (warm-up, exposures, the capture loop),
                  acquisition_journal (SESSION.partial, its journal, resuming) and
                  acquisition_session (the band images written as a session)
    command       `spherejax acquire`, added to spherejax's command line through the
                  "spherejax.commands" entry points (pyproject.toml)

It installs as `spherejax_hw`, so that no other package named `hw` can shadow it. It uses
spherejax (to render frames for the simulated camera, to write sessions and for the command
line); spherejax never imports it.
"""
