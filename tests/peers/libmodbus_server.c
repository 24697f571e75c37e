#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <modbus.h>

/* libmodbus's own TCP server, for tests and benchmarks: holding register i (0..999) holds
   1000 + i; one client at a time. Prints READY once listening. Built with CHANGING defined
   (bench/polling_cpu.py --changing), registers 0..9 count up after every reply, so no two
   reads of them return the same values. */
int main(int argc, char **argv)
{
    modbus_t *ctx = modbus_new_tcp("127.0.0.1", atoi(argv[1]));
    modbus_mapping_t *map = modbus_mapping_new(0, 0, 1000, 0);
    uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
    for (int i = 0; i < 1000; i++) map->tab_registers[i] = 1000 + i;
    int listener = modbus_tcp_listen(ctx, 4);
    if (listener < 0) { perror("listen"); return 1; }
    printf("READY\n");
    fflush(stdout);
    for (;;) {
        if (modbus_tcp_accept(ctx, &listener) < 0) continue;
        for (;;) {
            int rc = modbus_receive(ctx, query);
            if (rc > 0) modbus_reply(ctx, query, rc, map);
#ifdef CHANGING
            if (rc > 0) for (int i = 0; i < 10; i++) map->tab_registers[i]++;
#endif
            else if (rc == -1) break;
        }
        close(modbus_get_socket(ctx));
    }
}
