"""The ``estop`` sub-commands, one module each (``add_parser`` adds its parser, whose
``handler`` runs it), above everything else of the package; and what they share: the option
vocabulary (:mod:`~estop.commands.options`), the common settings (:mod:`~estop.commands.settings`
over :mod:`~estop.commands.configfile`), the output (:mod:`~estop.commands.output`) and the CAN
bus configuration (:mod:`~estop.commands.canbus`)."""
